"""Run a ``bonded_punch`` scene: load stepping with cut-back on failure; the loop, outputs,
checkpoints and restart are :mod:`coupling.runner`'s.

Output directory layout::

    scene.toml            the scene as run (with --set overrides applied)
    run.json              the run's fingerprint (coupling.rundir): the directory is this run's
    history.json / .csv   settlement, punch force, iterations, wall time per step
    continuum_*.bp        VTX series of u, phi, sigma, m (ParaView)
    particles_*.vtu, particles.pvd   the grains (displacement, rotation, kind), one series
    checkpoint/           last converged state (FE dofs per rank, step index, manifest.json
                          with sha256s; coupling.checkpoints), checkpoint.prev/ the one before
    last_good/            the last converged state of a failed solve
    *.png                 force-settlement curve and the particles over the continuum
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np

from coupling.apps.punch.model import coupled_window, fe_block, lattice_block
from coupling.apps.punch.scene import Scene
from coupling.preflight import memory_mb
from coupling.runner import Outputs, RunStopped, run_steps
from coupling.scene import load_scene
from coupling.staggered import InterfaceDidNotConverge, StaggeredOptions
from granfe.solvers import SolveDidNotConverge

__all__ = ["run_scene", "restart_scene", "execute", "summarise_punch", "RunStopped", "PunchSteps"]


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


def run_scene(scene: Scene, out: str | Path, comm=MPI.COMM_WORLD, progress: bool = True,
              start_step: int = 0, checkpoint: str | Path | None = None, stop=None,
              meta: dict | None = None) -> dict:
    """Run a ``bonded_punch`` scene into ``out`` (:func:`coupling.runner.run_steps`); returns
    the history. A checkpoint is written before the first step and after every step;
    ``start_step`` > 0 continues from ``checkpoint`` (default ``out/checkpoint``)."""
    out = Path(out)
    if comm.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        if not start_step:
            (out / "scene.toml").write_text(scene.to_toml())
    comm.barrier()
    steps = PunchSteps(scene, out, comm, start_step,
                       out / "checkpoint" if checkpoint is None else Path(checkpoint))
    outputs = Outputs(frame_every=scene.output.every, fields=scene.output.fields,
                      particles=scene.output.particles, png=scene.output.png, checkpoint_every=1,
                      checkpoint_at_start=True, checkpoint_at_end=True)
    history = run_steps(steps, out, comm, outputs, progress=progress, stop=stop, meta=meta,
                        header={"scene": scene.to_dict()})
    return {"steps": history}


class PunchSteps:
    """The punch pressed in ``penetrator.steps`` equal settlements, each cut back (halved)
    up to ``solver.cutbacks`` times when the staggered iteration or a solve fails
    (:class:`coupling.runner.Steps`)."""

    unit, history_name, particle_name, failures = "step", "history", "particles", ()

    def __init__(self, scene: Scene, out: Path, comm, start_step: int, checkpoint: Path):
        self.scene, self.out, self.comm, self.name = scene, out, comm, scene.scene.name
        g, p, w, pen, s = scene.geometry, scene.particles, scene.window, scene.penetrator, scene.solver
        self.block = lattice_block(g.width, g.height, p.radius, p.kn, p.kt, p.kr_factor, pen.width)
        # a failed solve writes its last converged state here (the checkpoints stay intact)
        self.problem = fe_block(comm, self.block, g.element_size, (g.degree_u, g.degree_phi),
                                prefix="scene_", checkpoint_dir=out / "last_good")
        self.run = coupled_window(self.block, self.problem, w.half_width, w.depth,
                                  w.ghost_width * 2 * p.radius, w.handshake * g.element_size,
                                  StaggeredOptions(tol=s.tol, max_iterations=s.max_iterations))
        self.n_steps = pen.steps
        self.history: list[dict] = []
        if start_step:
            self.problem.read_checkpoint(checkpoint)
            state = json.loads((checkpoint / "state.json").read_text())
            # rows after the checkpoint's step (written before a kill) are computed again
            rows = state.get("history")
            if rows is None and (out / "history.json").exists():   # a checkpoint of an older run
                rows = json.loads((out / "history.json").read_text())["steps"]
            self.history = [h for h in rows or [] if h["step"] <= start_step]

    def advance(self) -> dict:
        pen, s = self.scene.penetrator, self.scene.solver
        step = len(self.history)
        settled, target = pen.settlement * step / pen.steps, pen.settlement * (step + 1) / pen.steps
        t0 = time.perf_counter()
        increments, done = 1, settled
        while done < target - 1e-15 * pen.settlement:
            trial = min(target, done + (target - settled) / increments)
            try:
                its = self.run.press(trial)
                done = trial
            except (InterfaceDidNotConverge, SolveDidNotConverge) as err:
                increments *= 2
                if increments > 2**s.cutbacks:
                    self.problem.write_checkpoint()
                    raise RunStopped(
                        f"step {step + 1} (settlement {trial:.4g} m) failed after {s.cutbacks} "
                        f"cut-backs: {err}. Last good state (step {step}) is the checkpoint in "
                        f"{self.out / 'checkpoint'}; continue with `granfe restart {self.out}` after "
                        f"changing solver.* (or penetrator.steps) in {self.out / 'scene.toml'}") from err
        self.history.append({"step": step + 1, "settlement": target, "punch_force": self.run.punch_force(),
                             "iterations": its, "wall_time_s": time.perf_counter() - t0})
        return self.history[-1]

    def frame_time(self, record: dict) -> float:
        return float(record["step"])

    def particles(self) -> dict:
        c = self.run.coupling
        x = self.run.particles.assembly.x.copy()
        x[:, :2] += c.u
        u3 = np.zeros((len(x), 3))
        u3[:, :2] = c.u
        return {"x": x, "radius": np.full(len(x), self.scene.particles.radius), "displacement": u3,
                "rotation": np.asarray(c.theta, dtype=float), "kind": c.kinds.astype(float)}

    def postfix(self, record: dict) -> dict:
        return {"settlement": f"{record['settlement']:.3g} m", "force": f"{record['punch_force']:.3g} N/m",
                "step_time": f"{record['wall_time_s']:.2f} s"}

    def save_checkpoint(self, directory: Path, meta: dict | None) -> None:
        from coupling.checkpoints import write_checkpoint

        comm, step = self.comm, len(self.history)

        def files(tmp: Path) -> list[str]:
            self.problem.write_checkpoint(tmp)
            names = [f"continuum_rank{comm.rank}_of{comm.size}.npz"]
            if comm.rank == 0:
                (tmp / "state.json").write_text(json.dumps({"step": step, "history": self.history}))
                names.append("state.json")
            return names
        write_checkpoint(directory, step, comm, files, meta=meta)

    def save_last_good(self, where: Path) -> None:
        self.problem.write_checkpoint(where)

    def stopped(self, err: BaseException, where: Path) -> str:
        return f"{err}; the last good state is in {where}"

    def finish(self) -> None:
        """No columns derived from the whole history."""

    def figures(self, out: Path) -> None:
        _figures(out, self.problem, self.run, self.history, self.comm)


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
