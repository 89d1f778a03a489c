"""Run a coupled penetration with outputs: q_c / f_s against depth (CSV, JSON, PNG), grains
(VTU/PVD), continuum (VTX), a picture of both, and checkpoints every k FE steps (the loop
and its outputs: :mod:`coupling.runner`). Used by
``granfe run`` / ``granfe restart`` (kind ``penetration``) and ``demos/2d/cpt_coupled.py``."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401

import numpy as np

from coupling.apps.penetration.coupled import VERTICAL, CoupledPenetration, PenetrationParameters
from coupling.apps.penetration.penetrators import filtered
from coupling.collective_gc import collective_gc
from coupling.preflight import memory_mb
from coupling.runner import Outputs, run_steps

__all__ = ["run_penetration", "PenetrationSteps"]


def run_penetration(prm: PenetrationParameters, out: str | Path, comm, *, frames: int = 5,
                    fields: bool = True, particles: bool = True, png: bool = True,
                    progress: bool = True, log=None, checkpoint_every: int = 0,
                    restart: bool = False, moving=None, checkpoint=None, stop=None,
                    meta: dict | None = None, fluid=None) -> dict:
    """Set up, run and write a coupled penetration into ``out``; returns the results dict.

    The loop, frames, checkpoints and stops are :func:`coupling.runner.run_steps`'s.
    ``checkpoint_every`` > 0 writes ``out/checkpoint`` every that many FE steps (not after the
    last); ``restart`` continues from it (same parameters and rank count) instead of settling.
    ``moving`` (:class:`~coupling.apps.penetration.parameters.MovingWindowParameters`): the
    window follows the penetrator to ``moving.depth`` (no checkpoints); ``results.json`` then
    lists the moves. ``checkpoint``: the directory a restart continues from (default
    ``out/checkpoint``); ``meta`` goes into every checkpoint's manifest (the run's
    fingerprint); ``stop`` (:class:`coupling.interrupts.StopRequests`): after an FE step on
    which a signal arrived, write a checkpoint and raise
    :class:`coupling.interrupts.Interrupted`. ``fluid``
    (:class:`~coupling.apps.penetration.fluid.FluidParameters`): saturated, with a pore fluid
    (:mod:`coupling.apps.penetration.saturated`; checkpoints with the fluid's state, no
    moving window).
    """
    out = Path(out)
    checkpoint = out / "checkpoint" if checkpoint is None else Path(checkpoint)
    if restart and not (checkpoint / "state.json").exists():
        raise FileNotFoundError(f"no complete checkpoint in {checkpoint} to restart from "
                                "(output.checkpoint_every = 0, or the run stopped before the first)")
    if fluid is not None and moving is not None:
        raise ValueError("a saturated penetration keeps its window so far: moving must be None")
    if moving is not None and (restart or checkpoint_every):
        raise ValueError("a window that follows the penetrator writes no checkpoints yet: "
                         "checkpoint_every must be 0 and restart False")
    log = log or (lambda msg: print(msg, flush=True) if comm.rank == 0 else None)
    if comm.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    comm.barrier()
    t0 = time.perf_counter()
    with collective_gc(comm):
        cpt = _set_up(prm, comm, log, moving, checkpoint if restart else None, out, fluid)
    t_setup = time.perf_counter() - t0
    start = len(cpt.history)
    m = cpt.material_fe
    log(f"set-up {t_setup:.1f} s: {cpt.n_grains} grains, {len(cpt.pen_index)} penetrator spheres, "
        f"coordination {cpt.contact_stats['coordination']:.2f}; continuum lam = mu = {m.lam:.3g} Pa, "
        f"kappa = {m.kappa:.3g} Pa, rho = {m.rho:.0f} kg/m^3, "
        f"{cpt.problem.V.dofmap.index_map.size_global * cpt.problem.V.dofmap.index_map_bs} dofs")
    outputs = Outputs(frame_every=max(1, cpt.n_steps // frames), fields=fields, particles=particles,
                      png=png, checkpoint_every=checkpoint_every)
    t0 = time.perf_counter()
    steps = PenetrationSteps(cpt, moving is None)
    history = run_steps(steps, out, comm, outputs, progress=progress, stop=stop, meta=meta)
    t_run = time.perf_counter() - t0
    pushed = history[start:]
    results = {"parameters": prm.__dict__, "grains": cpt.n_grains,
               "penetrator_spheres": len(cpt.pen_index),
               "continuum": {"lam": m.lam, "mu": m.mu, "kappa": m.kappa, "gamma": m.gamma, "rho": m.rho,
                             "dofs": cpt.problem.V.dofmap.index_map.size_global
                             * cpt.problem.V.dofmap.index_map_bs},
               "packing": cpt.contact_stats, "dem_dt": cpt.sim.dt, "fe_dt": cpt.dt_fe,
               "dem_steps": cpt.sim.nsteps, "setup_time_s": t_setup, "run_time_s": t_run,
               "fe_steps_run": len(pushed), "restarted_from_step": start,
               "wall_time_per_fe_step_s": float(np.median([h["wall_time"] for h in pushed])) if pushed else None,
               "ranks": comm.size, "history": history, "window_moves": getattr(cpt, "moves", []),
               "q_c_mean_last_half": float(np.mean([h["q_c"] for h in history[len(history) // 2:]])),
               "filter_window_m": steps.filter_window}
    if fluid is not None:
        results["fluid"] = cpt.summary()
    if comm.rank == 0:
        (out / "results.json").write_text(json.dumps(results, indent=2, default=float))
        log(f"{len(pushed)} FE steps, {cpt.sim.nsteps} DEM steps in {t_run:.1f} s; outputs in {out}")
    return results


def _set_up(prm, comm, log, moving, checkpoint, out, fluid=None):
    """The coupled penetration, settled (or read from ``checkpoint``); a failure while
    settling or deriving the continuum keeps the grains' last good state in ``out/last_good``."""
    from dem.errors import BlowUpError, DemError
    from dem.io import save_state

    try:
        if fluid is not None:
            from coupling.apps.penetration.saturated import SaturatedPenetration
            return SaturatedPenetration(prm, fluid, comm, log=log, checkpoint=checkpoint)
        if moving is None:
            return CoupledPenetration(prm, comm, log=log, checkpoint=checkpoint)
        from coupling.apps.penetration.moving_window import MovingWindowPenetration
        return MovingWindowPenetration(prm, moving, comm, log=log)
    except (BlowUpError, DemError, FloatingPointError, ValueError) as err:
        if checkpoint is not None:   # the grains are the unsettled lattice: nothing worth keeping
            raise RuntimeError(f"restart from {checkpoint} failed: {err}") from err
        where = out / "last_good"
        path, grains = getattr(err, "path", None), getattr(err, "grains", None)
        kept = bool(path and Path(path).exists()) or grains is not None
        if comm.rank == 0 and kept:
            where.mkdir(parents=True, exist_ok=True)
            if path and Path(path).exists():  # a blow-up: the state before it, not the NaNs
                shutil.move(path, where / "grains.npz")
            else:
                save_state(where / "grains.npz", **grains)
        raise RuntimeError(f"penetration set-up failed: {err}"
                           + (f"; the grains' last state is in {where}" if kept else "")) from err


class PenetrationSteps:
    """A built :class:`CoupledPenetration` (or moving-window run) as the runner's
    :class:`coupling.runner.Steps`: one FE step per step, q_c / f_s per record."""

    name, unit, history_name, particle_name = "penetration", "FE step", "tip_resistance", "grains"

    def __init__(self, cpt: CoupledPenetration, checkpoints: bool):
        from coupling.apps.penetration.coupled import CouplingUnstable
        from dem.errors import BlowUpError, DemError

        self.cpt, self.checkpoints = cpt, checkpoints
        self.problem, self.history, self.n_steps = cpt.problem, cpt.history, cpt.n_steps
        self.filter_window = 2 * cpt.prm.cone_radius   # one cone diameter
        self.failures = (BlowUpError, DemError, CouplingUnstable, FloatingPointError, ValueError)

    def advance(self) -> dict:
        return self.cpt.advance()

    def frame_time(self, record: dict) -> float:
        return float(record["time"])

    def particles(self) -> dict:
        p = self.cpt.grain_state()
        return {"x": p.x, "radius": p.radius, "velocity": p.v, "kind": p.kind.astype(float), "force": p.force}

    def postfix(self, record: dict) -> dict:
        return {"depth": f"{record['depth'] * 1e3:.1f} mm", "q_c": f"{record['q_c'] / 1e3:.2f} kPa",
                "step": f"{record['wall_time']:.2f} s"}

    def save_checkpoint(self, directory: Path, meta: dict | None) -> None:
        if self.checkpoints:
            self.cpt.save_checkpoint(directory, meta=meta)

    def save_last_good(self, where: Path) -> None:
        from dem.io import save_state

        self.cpt.problem.write_checkpoint(where)
        p = self.cpt.grain_state()
        if self.cpt.comm.rank == 0:
            save_state(where / "grains.npz", **p.state_dict())

    def stopped(self, err: BaseException, where: Path) -> str:
        depth = self.history[-1]["depth"] if self.history else 0.0
        return (f"penetration stopped at depth {depth:.4g} m: {err}; the last state and the "
                f"history so far are in {where}")

    def finish(self) -> None:
        """The smoothed profiles beside the raw ones (``q_c_filtered``, ``f_s_filtered``)."""
        wet = bool(self.history) and "u2" in self.history[0]   # (a saturated run)
        for key in ("q_c", "f_s") + (("u2", "q_t") if wet else ()):
            for h, v in zip(self.history, filtered(self.history, key, self.filter_window), strict=True):
                h[f"{key}_filtered"] = float(v)

    def figures(self, out: Path) -> None:
        _picture(self.cpt, out / "cpt.png")
        if self.cpt.comm.rank == 0:
            _curves(self.history, out / "tip_resistance.png")


def _curves(history, path):
    """q_c, f_s (raw and filtered) and the friction ratio against depth, as CPT logs are drawn."""
    import matplotlib.pyplot as plt

    depth = np.array([h["depth"] for h in history]) * 100
    wet = "u2" in history[0]   # (a saturated run: u2 beside)
    fig, axes = plt.subplots(1, 4 if wet else 3, figsize=(13 if wet else 10, 5), sharey=True)
    for ax, key, label in ((axes[0], "q_c", "tip resistance q_c [kPa]"),
                           (axes[1], "f_s", "sleeve friction f_s [kPa]")):
        ax.plot([h[key] / 1e3 for h in history], depth, color="0.7", lw=0.8, label="raw")
        if f"{key}_filtered" in history[0]:
            ax.plot([h[f"{key}_filtered"] / 1e3 for h in history], depth, color="C0",
                    label="over one cone diameter")
        ax.set_xlabel(label)
    axes[0].legend(loc="lower left")
    if "q_c_filtered" in history[0]:
        rf = [100 * h["f_s_filtered"] / h["q_c_filtered"] if h["q_c_filtered"] > 0 else np.nan for h in history]
        axes[2].plot(rf, depth)
    axes[2].set_xlabel("friction ratio f_s / q_c [%]")
    if wet:
        axes[3].plot([h["u2"] / 1e3 for h in history], depth, color="0.7", lw=0.8)
        if "u2_filtered" in history[0]:
            axes[3].plot([h["u2_filtered"] / 1e3 for h in history], depth, color="C0")
        axes[3].set_xlabel("pore pressure behind the cone u2 [kPa]")
    axes[0].set_ylabel("depth [cm]")
    axes[0].invert_yaxis()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _picture(cpt, path):
    """|u| of the continuum and the grains (red: ghosts and penetrator). 3D: the continuum's
    half y <= 0, cut open at y = 0, with the grains in a slab just in front of the cut."""
    from granfe.io import render_png

    prm, p = cpt.prm, cpt.grain_state()
    W, s = 0.5 * prm.chamber_width, cpt.surface
    # down to the lowest grain (a window that followed the cone reaches deeper)
    ax = VERTICAL[prm.dim]
    low = max(min(s - 0.12, float(p.x[: cpt.n_grains, ax].min()) - 4 * prm.radius), s - prm.chamber_depth)
    title = (f"displacement magnitude of the continuum [m]; grains (red: ghosts, {prm.shape}), depth "
             f"{cpt.depth * 100:.1f} cm")
    if prm.dim == 2:
        def overlay(plotter, warp):
            import pyvista
            # disks at their true radius, lifted off the continuum's plane so both show
            x = p.x.copy()
            x[:, 2] = 1e-3 * prm.chamber_width
            cloud = pyvista.PolyData(x)
            cloud["radius"] = p.radius.copy()
            cloud["kind"] = p.kind.astype(float)
            disks = cloud.glyph(scale="radius", orient=False,
                                geom=pyvista.Disc(inner=0.0, outer=1.0, r_res=1, c_res=16))
            plotter.add_mesh(disks, scalars="kind", cmap=["white", "red"], show_scalar_bar=False,
                             show_edges=False)

        render_png(cpt.problem, path, "u_magnitude", warp=0, overlay=overlay,
                   box=(-W / 2, W / 2, low, s + 0.03), title=title)
        return
    d = 2 * prm.radius
    slab = (p.x[:, 1] >= -0.5 * d) & (p.x[:, 1] <= 1.5 * d)
    slab[cpt.pen_index] = p.x[cpt.pen_index, 1] >= 0

    def overlay(plotter, warp):
        import pyvista
        cloud = pyvista.PolyData(p.x[slab].copy())
        cloud["radius"] = p.radius[slab].copy()
        cloud["kind"] = p.kind[slab].astype(float)
        balls = cloud.glyph(scale="radius", orient=False,
                            geom=pyvista.Sphere(radius=1.0, theta_resolution=10, phi_resolution=10))
        plotter.add_mesh(balls, scalars="kind", cmap=["white", "red"], show_scalar_bar=False)

    reach = 1.5 * (prm.window_half_width + prm.ghost_width * d)
    render_png(cpt.problem, path, "u_magnitude", warp=0, overlay=overlay,
               box=(-reach, reach, -reach, 0.0, min(s - 1.5 * prm.window_depth, low), s + 0.01), title=title)


def execute(scene, out, comm, *, progress: bool = True, checkpoint=None, stop=None,
            meta: dict | None = None) -> None:
    """The ``penetration`` application's run (its row in :mod:`coupling.applications`)."""
    o = scene.output
    run_penetration(scene.parameters(), out, comm, frames=o.frames, fields=o.fields,
                    particles=o.particles, png=o.png, progress=progress,
                    checkpoint_every=o.checkpoint_every, restart=checkpoint is not None,
                    moving=scene.moving_parameters(), checkpoint=checkpoint, stop=stop, meta=meta,
                    fluid=scene.fluid_parameters())


def summarise_penetration(scene, ranks: int = 1) -> dict:
    """Sizes and cost estimates of a ``penetration`` scene (see
    :func:`coupling.applications.summarise`)."""
    from coupling.apps.penetration.coupled import contact_material, dem_time_step

    prm = scene.parameters()
    d = 2 * prm.radius
    band = prm.ghost_width * d
    dim = prm.dim
    if dim == 2:
        area = (2 * (prm.window_half_width + band)) * (prm.window_depth + band)
        grains = area / (np.sqrt(3) / 2 * d * d)
    else:  # fcc with a gap of 2 % of a diameter (coupling.apps.penetration.coupled.grain_lattice)
        volume = (2 * (prm.window_half_width + band)) ** 2 * (prm.window_depth + band)
        grains = volume * 0.74 / 1.02**3 / (np.pi / 6 * d**3)
    from dem import Particles, critical_dt
    from dem.timestep import DEFAULT_SAFETY

    r_min = np.array([prm.radius * (1 - prm.jitter)])
    dt = dem_time_step(prm, r_min)
    if dt is None:
        # the DEM's default step counts every disk, the cone's (half a grain radius) too
        r_min = np.minimum(r_min, 0.5 * prm.radius)
        probe = Particles.spheres(np.zeros((1, 3)), r_min, prm.density, dim=2)
        dt = DEFAULT_SAFETY["linear"] * critical_dt(probe, [contact_material(prm)])  # the DEM's default
    dt *= prm.dt_factor
    settle = prm.settle_time / dt
    if prm.vertical_stress > 0:
        # consolidation (coupling.apps.penetration.chamber): about 20 periods of the window's
        # slowest mode, a quarter wave over its height (measured: 30k steps for a 10 cm window)
        wave = np.sqrt(prm.kn / prm.density)
        settle = 20 * 4 * (prm.window_depth + band) / wave / dt
    # the size field ramps from fine to coarse over about the window size again
    hw, hf = prm.element_size_window, prm.element_size_far
    if dim == 2:   # 0.87-0.91 of the gmsh meshes' nodes without the factor 1.1
        window_cells = 4 * (2 * (prm.window_half_width + band) * (prm.window_depth + band)) / hw**2
        far_cells = 2 * prm.chamber_width * prm.chamber_depth / hf**2
        nodes = 1.1 * (window_cells + far_cells) / 2
        fine = window_cells > far_cells
    else:
        # fitted to 9 gmsh chambers (h_window 4-10 mm, h_far 2-8 cm; within 3 %): the refined
        # cylinder's volume and surface in h_window, the chamber's volume in h_far
        rw, dw = np.sqrt(2) * (prm.window_half_width + band), prm.window_depth + band
        surface = np.pi * rw**2 + 2 * np.pi * rw * dw
        window = 0.97 * np.pi * rw**2 * dw / hw**3 + 1.66 * surface / hw**2
        far = 0.68 * np.pi * prm.chamber_width**2 / 4 * prm.chamber_depth / hf**3
        nodes, fine = window + far, window > far
    dofs = (3 if dim == 2 else 6) * nodes
    depth = scene.penetrator.depth   # the whole push (more than prm.depth if the window follows)
    out = {"kind": "penetration", "dimension": dim, "grains_in_window_and_ghost_band": int(grains),
           "fe_dofs_estimate": int(dofs), "dem_time_step_estimate_s": float(dt),
           "dem_steps_estimate": int(settle + depth / prm.velocity / dt),
           "fe_steps": int(np.ceil(depth / prm.velocity / (prm.substeps * dt))),
           "memory_estimate_MB_per_rank": memory_mb(1.25 * grains, dofs / ranks)}
    fe_heavy = 0.0025 * dofs / ranks > 0.024 * 1.25 * grains
    out["memory_driver"] = (("chamber.element_size_window" if fine else "chamber.element_size_far")
                            if fe_heavy else "grains.radius")
    mv = scene.moving_parameters()
    if mv is not None:
        # each move adds ``step`` diameters of window depth (fewer once it travels)
        tip_room = prm.window_depth - mv.trigger * d
        moves = max(0, int(np.ceil((depth - tip_room) / (mv.step * d))))
        out.update(window_follows=True, window_moves_estimate=moves,
                   dem_steps_estimate=out["dem_steps_estimate"] + moves * mv.settle_steps)
    from coupling.preflight import run_time_s

    out["run_time_estimate_s"] = round(run_time_s(dim, 1.25 * grains, out["dem_steps_estimate"],
                                                  out["fe_steps"], dofs, ranks), 0)
    return out


def penetration_checks(scene, info) -> list[str]:
    """Push velocity against the DEM time step (refused by key), gravity and cone warnings."""
    from coupling.apps.penetration.coupled import check_push
    from coupling.scene import SceneError

    prm = scene.parameters()
    try:
        check_push(prm, info["dem_time_step_estimate_s"])
    except ValueError as err:
        raise SceneError(f"penetrator.{err}") from None
    warnings = []
    g = scene.grains.gravity
    if g < 0:
        warnings.append(f"grains.gravity = {g} points up (the grains are pulled away from the "
                        "chamber's base; gravity is the magnitude pointing down, e.g. 9.81)")
    elif g == 0:
        warnings.append("grains.gravity = 0: the grains do not settle into a load-bearing packing")
    if scene.penetrator.shape == "cone" and scene.penetrator.apex_deg > 120:
        warnings.append(f"penetrator.apex_deg = {scene.penetrator.apex_deg} is a nearly flat "
                        "cone (the standard cone is 60 degrees)")
    if info.get("run_time_estimate_s", 0) > 24 * 3600:
        warnings.append(f"the run takes about {info['run_time_estimate_s'] / 3600:.0f} h by the "
                        "rough estimate")
    return warnings
