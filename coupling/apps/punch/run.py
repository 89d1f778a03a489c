"""Run a scene: load stepping, cut-back on failure, outputs, checkpoints and restart.

Output directory layout::

    scene.toml            the scene as run (with --set overrides applied)
    run.json              the run's fingerprint (coupling.rundir): the directory is this run's
    history.json / .csv   settlement, punch force, iterations, wall time per step
    continuum_*.bp        VTX series of u, phi, sigma, m (ParaView)
    particles/*.vtu, particles.pvd
    checkpoint/           last converged state (FE dofs per rank, step index, manifest.json
                          with sha256s; coupling.checkpoints), checkpoint.prev/ the one before
    last_good/            the last converged state of a failed solve
    *.png                 force-settlement curve and the particles over the continuum
"""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np

from coupling.apps.punch.model import coupled_window, fe_block, lattice_block
from coupling.apps.punch.scene import Scene
from coupling.checkpoints import ensure_free_space
from coupling.collective_gc import collect, collective_gc
from coupling.preflight import memory_mb
from coupling.scene import load_scene
from coupling.staggered import InterfaceDidNotConverge, StaggeredOptions
from granfe.solvers import SolveDidNotConverge

__all__ = ["run_scene", "restart_scene", "execute", "summarise_punch", "RunStopped"]


class RunStopped(RuntimeError):
    """A step failed after all cut-backs; the message says where the last good state is."""


def _write_particles(out: Path, step: int, t: float, x, u, theta, kinds, series: list):
    import meshio

    out.mkdir(parents=True, exist_ok=True)
    name = f"particles_{step:05d}.vtu"
    pts = x.copy()
    pts[:, :2] += u
    u3 = np.zeros((len(x), 3))
    u3[:, :2] = u
    meshio.write(out / name, meshio.Mesh(pts, [("vertex", np.arange(len(x))[:, None])],
                                         point_data={"displacement": u3, "rotation": theta,
                                                     "kind": kinds.astype(np.int32)}))
    series.append((t, f"particles/{name}"))
    entries = "\n".join(f'    <DataSet timestep="{tt:.9g}" file="{f}"/>' for tt, f in series)
    (out.parent / "particles.pvd").write_text(
        '<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n  <Collection>\n'
        f"{entries}\n  </Collection>\n</VTKFile>\n")


def summarise_punch(scene, ranks: int = 1) -> dict:
    """Sizes and cost estimates of a ``bonded_punch`` scene (see
    :func:`coupling.applications.summarise`)."""
    g, p, w = scene.geometry, scene.particles, scene.window
    d = 2 * p.radius
    grains_block = (g.width / d) * (g.height / (d * np.sqrt(3) / 2))
    window_area = (2 * w.half_width + 2 * w.ghost_width * d) * (w.depth + w.ghost_width * d)
    grains_window = window_area / (np.sqrt(3) / 2 * d * d)
    cells = 2 * (g.width / g.element_size) * (g.height / g.element_size)
    nodes_u = (2 * g.width / g.element_size + 1) * (2 * g.height / g.element_size + 1) if g.degree_u == 2 \
        else (g.width / g.element_size + 1) * (g.height / g.element_size + 1)
    nodes_p1 = (g.width / g.element_size + 1) * (g.height / g.element_size + 1)
    nodes_phi = nodes_u if g.degree_phi == g.degree_u else nodes_p1
    dofs = 2 * nodes_u + nodes_phi
    return {
        "kind": scene.scene.kind, "dimension": scene.scene.dimension,
        "fe_cells": int(cells), "fe_dofs": int(dofs),
        "grains_in_window_and_ghost_band": int(grains_window),
        "grains_if_all_dem": int(grains_block),
        "load_steps": scene.penetrator.steps,
        "memory_estimate_MB_per_rank": memory_mb(grains_window, dofs / ranks),
        "memory_driver": "geometry.element_size",
        "time_step": "quasi-static (no explicit time step)",
        # one sparse direct solve per staggered iteration, ~10 iterations per load step
        "run_time_estimate_s": round(5.0 + scene.penetrator.steps * 10
                                     * (0.02 + 2e-5 * dofs / ranks), 0),
    }


def run_scene(scene: Scene, out: str | Path, comm=MPI.COMM_WORLD, **kwargs) -> dict:
    """Run a ``bonded_punch`` scene: :func:`_run_scene`, with cyclic garbage collected at the
    same points on every rank (:mod:`coupling.collective_gc`)."""
    with collective_gc(comm):
        return _run_scene(scene, out, comm, **kwargs)


def _run_scene(  # noqa: C901 (the next to split: one runner for every application)
    scene: Scene, out: str | Path, comm=MPI.COMM_WORLD, progress: bool = True,
              start_step: int = 0, checkpoint: str | Path | None = None, stop=None,
              meta: dict | None = None) -> dict:
    """Run a ``bonded_punch`` scene into ``out``; returns the history.

    A checkpoint (:mod:`coupling.checkpoints`, ``meta`` in its manifest) is written before
    the first step and after every step; ``start_step`` > 0 continues from ``checkpoint``
    (default ``out/checkpoint``). ``stop`` (:class:`coupling.interrupts.StopRequests`): after
    a step on which a signal arrived, raise :class:`coupling.interrupts.Interrupted`."""
    from coupling.checkpoints import write_checkpoint
    from coupling.interrupts import Interrupted

    out = Path(out)
    checkpoint = out / "checkpoint" if checkpoint is None else Path(checkpoint)
    if comm.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        if not start_step:
            (out / "scene.toml").write_text(scene.to_toml())
    comm.barrier()
    g, p, w, pen, s = scene.geometry, scene.particles, scene.window, scene.penetrator, scene.solver
    block = lattice_block(g.width, g.height, p.radius, p.kn, p.kt, p.kr_factor, pen.width)
    # a failed solve writes its last converged state here (the checkpoints stay intact)
    problem = fe_block(comm, block, g.element_size, (g.degree_u, g.degree_phi), prefix="scene_",
                       checkpoint_dir=out / "last_good")
    run = coupled_window(block, problem, w.half_width, w.depth, w.ghost_width * 2 * p.radius,
                         w.handshake * g.element_size,
                         StaggeredOptions(tol=s.tol, max_iterations=s.max_iterations))
    history_path = out / "history.json"
    history = []
    if start_step and history_path.exists():
        # rows after the checkpoint's step (written before a kill) are computed again
        rows = json.loads(history_path.read_text())["steps"]
        history = [h for h in rows if h["step"] <= start_step]
    if start_step:
        problem.read_checkpoint(checkpoint)

    def save(step: int):
        def files(tmp: Path) -> list[str]:
            problem.write_checkpoint(tmp)
            names = [f"continuum_rank{comm.rank}_of{comm.size}.npz"]
            if comm.rank == 0:
                (tmp / "state.json").write_text(json.dumps({"step": step}))
                names.append("state.json")
            return names
        write_checkpoint(out / "checkpoint", step, comm, files, meta=meta)

    if not start_step:
        save(0)   # the initial state: a failure in step 1 can be continued after a fix
    writer = None
    if scene.output.fields:
        from granfe.io import ContinuumWriter
        writer = ContinuumWriter(problem, out, name=f"continuum_from{start_step:04d}")
    # the particle frames of the steps before the restart stay in particles.pvd
    series: list = _pvd_entries(out / "particles.pvd", start_step) if start_step else []
    bar = None
    if progress and comm.rank == 0:
        from tqdm import tqdm
        bar = tqdm(total=pen.steps, initial=start_step, unit="step", desc=scene.scene.name)
    settled = pen.settlement * start_step / pen.steps
    for step in range(start_step, pen.steps):
        target = pen.settlement * (step + 1) / pen.steps
        t0 = time.perf_counter()
        increments, done = 1, settled
        while done < target - 1e-15 * pen.settlement:
            trial = min(target, done + (target - settled) / increments)
            try:
                its = run.press(trial)
                done = trial
            except (InterfaceDidNotConverge, SolveDidNotConverge) as err:
                increments *= 2
                if increments > 2**s.cutbacks:
                    problem.write_checkpoint()
                    raise RunStopped(
                        f"step {step + 1} (settlement {trial:.4g} m) failed after {s.cutbacks} "
                        f"cut-backs: {err}. Last good state (step {step}) is the checkpoint in "
                        f"{out / 'checkpoint'}; continue with `granfe restart {out}` after "
                        f"changing solver.* (or penetrator.steps) in {out / 'scene.toml'}") from err
        settled = target
        elapsed = time.perf_counter() - t0
        history.append({"step": step + 1, "settlement": target, "punch_force": run.punch_force(),
                        "iterations": its, "wall_time_s": elapsed})
        if step % scene.output.every == 0 or step + 1 == pen.steps:
            ensure_free_space(out, comm, "frame")
            collect(comm)
            if writer is not None:
                writer.write(float(step + 1))
            if scene.output.particles and comm.rank == 0:
                x = run.particles.assembly.x
                _write_particles(out / "particles", step + 1, float(step + 1), x, run.coupling.u,
                                 run.coupling.theta, run.coupling.kinds, series)
        if comm.rank == 0:
            history_path.write_text(json.dumps({"scene": scene.to_dict(), "steps": history}, indent=2))
            with open(out / "history.csv", "w", newline="") as f:
                wr = csv.DictWriter(f, fieldnames=list(history[0]))
                wr.writeheader()
                wr.writerows(history)
        save(step + 1)
        if bar is not None:
            bar.set_postfix(settlement=f"{target:.3g} m", force=f"{history[-1]['punch_force']:.3g} N/m",
                            step_time=f"{elapsed:.2f} s")
            bar.update(1)
        signum = stop.requested(comm) if stop is not None else 0
        if signum and step + 1 < pen.steps:
            if bar is not None:
                bar.close()
            if writer is not None:
                writer.close()
            raise Interrupted(signum, step + 1, out / "checkpoint", out)
    if bar is not None:
        bar.close()
    if writer is not None:
        writer.close()
    if scene.output.png:
        _figures(out, problem, run, history, comm)
    return {"steps": history}


def _pvd_entries(path: Path, last_step: int) -> list:
    """(time, file) of the frames in a ``.pvd`` collection up to ``last_step``."""
    import re

    if not path.exists():
        return []
    entries = re.findall(r'<DataSet timestep="([^"]+)" file="([^"]+)"/>', path.read_text())
    return [(float(t), f) for t, f in entries if float(t) <= last_step + 1e-9]


def _figures(out, problem, run, history, comm):
    from granfe.io import render_png

    x = run.particles.assembly.x
    u = run.coupling.u
    kinds = run.coupling.kinds

    def particles(plotter, warp):
        import pyvista
        pts = x.copy()
        pts[:, :2] += warp * u
        cloud = pyvista.PolyData(pts)
        cloud["kind"] = kinds.astype(float)
        plotter.add_mesh(cloud, scalars="kind", cmap=["white", "red"], point_size=4,
                         render_points_as_spheres=True, show_scalar_bar=False)

    render_png(problem, out / "particles_and_continuum.png", "u_y", overlay=particles,
               title="u_y of the continuum, grains (white: free, red: ghosts)")
    if comm.rank == 0:
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(5, 4))
        ax.plot([0] + [h["settlement"] * 1e3 for h in history], [0] + [h["punch_force"] for h in history], "o-")
        ax.set_xlabel("punch settlement [mm]")
        ax.set_ylabel("punch force [N/m]")
        fig.tight_layout()
        fig.savefig(out / "force_settlement.png", dpi=120)


def restart_scene(out: str | Path, comm=MPI.COMM_WORLD, progress: bool = True,
                  checkpoint: str | Path | None = None, stop=None,
                  meta: dict | None = None) -> dict:
    """Continue a run from its checkpoint (``out/checkpoint`` unless ``checkpoint``; same
    rank count)."""
    out = Path(out)
    checkpoint = out / "checkpoint" if checkpoint is None else Path(checkpoint)
    state = checkpoint / "state.json"
    if not state.exists():
        raise FileNotFoundError(f"no checkpoint in {out} (expected {state})")
    step = json.loads(state.read_text())["step"]
    scene = load_scene(out / "scene.toml")
    if scene.scene.kind != "bonded_punch":
        raise FileNotFoundError(f"restart_scene runs bonded_punch scenes; {scene.scene.kind!r} "
                                "scenes restart through coupling.apps.penetration.run.run_penetration")
    if step >= scene.penetrator.steps:
        if comm.rank == 0:
            print(f"granfe: the run in {out} is complete (step {step} of {scene.penetrator.steps}); "
                  "nothing to restart (raise penetrator.steps in its scene.toml to go further)",
                  flush=True)
        return json.loads((out / "history.json").read_text())
    return run_scene(scene, out, comm, progress=progress, start_step=step, checkpoint=checkpoint, stop=stop,
                     meta=meta)


def execute(scene, out, comm, *, progress: bool = True, checkpoint=None, stop=None,
            meta: dict | None = None) -> None:
    """The ``bonded_punch`` application's run (its row in :mod:`coupling.applications`)."""
    if checkpoint is not None:
        restart_scene(out, comm, progress=progress, checkpoint=checkpoint, stop=stop, meta=meta)
    else:
        run_scene(scene, out, comm, progress=progress, stop=stop, meta=meta)
