"""Checks a run performs before its first expensive step, shared by ``granfe check`` and
``granfe run`` / ``restart``: everything :func:`coupling.scene.load_scene` validates, plus what
needs a computed quantity: the push velocity against the DEM time step, the memory estimate
against the machine's memory (refused naming the key that drives it), a rough run time, and
warnings (gravity pointing up, a nearly flat cone).
"""

from __future__ import annotations

import os

from coupling.scene import SceneError

__all__ = ["preflight", "machine_memory_mb"]

# rough throughput of this code on one core (2026-12, coupled runs, numba kernels cached):
# particle-steps per second of the DEM (2D linear disks, 3D Hertz-Mindlin spheres)
_DEM_RATE = {2: 2.5e6, 3: 1.0e6}


def machine_memory_mb() -> float:
    """Physical memory of this machine [MB] (``/proc/meminfo`` MemTotal, else sysconf)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemTotal:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**20


def preflight(scene, ranks: int = 1) -> dict:
    """Sizes, estimates and warnings of ``scene`` run on ``ranks`` MPI ranks of this machine;
    raises :class:`SceneError` naming the key of anything the run would refuse later."""
    from coupling.applications import application

    app = application(scene.scene.kind)
    info = app.load("summarise")(scene, ranks)
    checks = app.load("checks")
    warnings = checks(scene, info) if checks is not None else []
    total = info["memory_estimate_MB_per_rank"] * ranks
    available = machine_memory_mb()
    info["machine_memory_MB"] = round(available, 0)
    if total > available:
        driver = info["memory_driver"]
        fix = (f"coarser elements (a larger {driver})" if driver.startswith(("chamber", "geometry"))
               else "fewer grains (a larger grains.radius or a smaller window) or fewer ranks "
                    "(the grains are replicated on every rank)")
        raise SceneError(
            f"{driver}: the run needs about {total / 1024:.1f} GB "
            f"({info['memory_estimate_MB_per_rank'] / 1024:.1f} GB on each of {ranks} rank(s)), "
            f"more than this machine's {available / 1024:.1f} GB; use {fix}")
    if total > 0.5 * available:
        warnings.append(f"the run needs about {total / 1024:.1f} GB, more than half of this "
                        f"machine's {available / 1024:.1f} GB ({info['memory_driver']} drives it)")
    info["warnings"] = warnings
    return info


def run_time_s(dim: int, grains: float, dem_steps: float, fe_steps: float, dofs: float,
               ranks: int = 1) -> float:
    """A rough wall time [s] (factor ~2): set-up, the DEM's particle-steps at the rate of
    ``_DEM_RATE`` (grains replicated on every rank, threads shared between them) and one
    sparse direct FE solve per FE step (~linear in the dofs at these sizes)."""
    dem = 1.15 * grains * dem_steps / _DEM_RATE[dim]
    fe = fe_steps * (0.02 + 4e-5 * dofs / max(ranks, 1))
    return float(5.0 + 1e-3 * dofs + dem + fe)


def memory_mb(particles: float, dofs: float) -> float:
    """Peak resident memory of one rank [MB], calibrated on this code (ru_maxrss of 3D
    penetration runs, 2026-12): ~550 MB of interpreter, dolfinx, PETSc and numba-compiled
    kernels, ~24 kB per particle (replicated on every rank: state, neighbour candidates with
    history, coupling operators) and ~2.5 kB per FE dof (matrix and LU fill)."""
    return round(550.0 + 0.024 * particles + 0.0025 * dofs, 0)
