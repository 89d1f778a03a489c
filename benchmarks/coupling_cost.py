"""Cost of the DE x FE coupling: time split (FE, particles, projection, operators) and error
against run time as the DE window and the overlap width vary.

Runs ``demos/2d/coupled_punch.py`` (bonded grains under a rough punch, full DEM reference)
for each overlap width, ``--repeat`` times, in fresh processes; the demo's own timers split
each coupled solve into FE solves, particle solves, projections and operator set-up.
Writes ``results.json`` (min and median over repeats) and ``coupling_cost.png``.

Second part (``--parts dem_phase``): the DEM phase of one coupled FE step of the ``make
demo`` scene (``scenes/cpt_2d.toml``: 1261 particles, 50 DEM steps per FE step), one rank,
``NUMBA_NUM_THREADS=1``, against one plain ``sim.step(substeps)`` on the same particles from
the same state (`dem.Simulation.state_dict` / ``load_state``), and against the per-step
Python loop the coupled runs used before the prescribed motions moved into the step loop
(ghosts and cone written before each ``step(1)``). Each FE step of ``--fe-steps`` measures
all three from the same state, then takes the real coupled step; min and median over them,
the CPU model from ``/proc/cpuinfo``, under ``dem_phase`` in ``results.json``.

Run: ``python benchmarks/coupling_cost.py [--ranks 1 2] [--parts punch dem_phase]``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from machine import cpu_model

ROOT = Path(__file__).resolve().parents[1]
SHORT = os.environ.get("GRANFE_SHORT") == "1"
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--out", type=Path, default=Path("output/coupling_cost"))
parser.add_argument("--repeat", type=int, default=1 if SHORT else 3)
parser.add_argument("--handshakes", type=float, nargs="+", default=[1.0, 2.0] if SHORT else [1.0, 2.0, 3.0])
parser.add_argument("--ranks", type=int, nargs="+", default=[1] if SHORT else [1, 2])
parser.add_argument("--parts", nargs="+", default=["punch", "dem_phase"],
                    choices=["punch", "dem_phase"])
parser.add_argument("--fe-steps", type=int, default=3 if SHORT else 9,
                    help="dem_phase: coupled FE steps measured (after 2 warm-up steps)")
parser.add_argument("--samples", type=int, default=3,
                    help="dem_phase: samples of each variant per FE step (interleaved)")
parser.add_argument("--dem-phase-worker", type=Path, help=argparse.SUPPRESS)
args = parser.parse_args()




def dem_phase_worker(path: Path):
    """(In a process of its own, NUMBA_NUM_THREADS=1.) Per FE step of the demo scene,
    ``samples`` times each from one state (restored with ``load_state``, interleaved so
    that a busy spell of the machine hits all alike): the plain ``sim.step(substeps)``,
    the coupled runs' DEM phase (`coupling.substep.sub_cycle`, as ``run`` calls it) and the
    old per-step Python loop; then the coupled FE step itself (its DEM phase from
    ``step_timings``, once per FE step)."""
    import time

    from mpi4py import MPI

    from coupling.apps.penetration.coupled import VERTICAL, CoupledPenetration
    from coupling.scene import load_scene
    from coupling.substep import GhostMotion, sub_cycle

    prm = load_scene(ROOT / "scenes/cpt_2d.toml").parameters()
    if SHORT:
        from dataclasses import replace
        prm = replace(prm, settle_time=0.05)
    cpt = CoupledPenetration(prm, MPI.COMM_SELF, log=lambda m: None)
    sim, n = cpt.sim, prm.substeps
    cpt.run(steps=2)  # compiles everything once

    def python_loop():
        """The coupled runs' DEM phase before the fused step (coupling/apps/penetration/coupled.py)."""
        p, g = sim.p, cpt.ghost_local
        g_prev, g_next = cpt.g_prev, cpt.interface.ghost_motion()
        down = np.eye(3)[VERTICAL[prm.dim]]
        depth = cpt.depth
        for s in range(1, n + 1):
            f = s / n
            x = cpt.x_ref[g].copy()
            x[:, :prm.dim] += (1 - f) * g_prev[0] + f * g_next[0]
            p.x[g] = x
            p.v[g, :prm.dim] = (g_next[0] - g_prev[0]) / cpt.dt_fe
            depth += prm.velocity * sim.dt
            p.x[cpt.pen_index] = cpt.pen0 + (-depth) * down
            p.v[cpt.pen_index] = -prm.velocity * down
            sim.step(1)

    def fused_phase():
        """What `CoupledPenetration.run` does for its DEM phase (coupling.substep)."""
        ghosts = GhostMotion(cpt.ghost_local, cpt.x_ref[cpt.ghost_local], cpt.g_prev[0],
                             cpt.interface.ghost_motion()[0], cpt.dt_fe)
        sub_cycle(sim, n, (cpt.pen_index, cpt.pen0), cpt.depth, prm.velocity,
                  VERTICAL[prm.dim], ghosts)

    variants = {"plain_step": lambda: sim.step(n), "coupled_dem_phase": fused_phase,
                "python_loop_before": python_loop}
    wall = {k: [] for k in variants}
    cpu = {k: [] for k in variants}
    coupled = []
    for _ in range(args.fe_steps):
        state = sim.state_dict()
        for _ in range(args.samples):  # interleaved, each from the same state
            for k, f in variants.items():
                t0, c0 = time.perf_counter(), time.process_time()
                f()
                wall[k].append(time.perf_counter() - t0)
                cpu[k].append(time.process_time() - c0)
                sim.load_state(state)
        cpt.run(steps=1)  # the coupled FE step itself, from the same state
        coupled.append(cpt.step_timings[-1]["dem"])

    def stats(v):
        return {"min_s": min(v), "median_s": float(np.median(v)), "all_s": v}

    out = {"scene": "scenes/cpt_2d.toml", "ranks": 1, "numba_threads": 1,
           "particles": int(sim.p.n), "substeps": n, "fe_steps": args.fe_steps,
           "samples_per_fe_step": args.samples, "cpu_model": cpu_model(),
           "note": "wall: perf_counter; cpu: process_time of this (single-threaded) process, "
                   "what other jobs on the machine do not inflate",
           "wall": {k: stats(v) for k, v in wall.items()},
           "cpu": {k: stats(v) for k, v in cpu.items()},
           "coupled_run_dem_phase_wall": stats(coupled)}
    for clock in ("wall", "cpu"):
        for k in ("min", "median"):
            t = out[clock]
            out[f"ratio_{clock}_{k}"] = (t["coupled_dem_phase"][f"{k}_s"]
                                         / t["plain_step"][f"{k}_s"])
            out[f"ratio_python_loop_{clock}_{k}"] = (t["python_loop_before"][f"{k}_s"]
                                                     / t["plain_step"][f"{k}_s"])
    path.write_text(json.dumps(out, indent=2))


def dem_phase():
    with tempfile.TemporaryDirectory() as tmp:
        res = Path(tmp) / "dem_phase.json"
        cmd = [sys.executable, __file__, "--dem-phase-worker", str(res),
               "--fe-steps", str(args.fe_steps), "--samples", str(args.samples)]
        env = dict(os.environ, NUMBA_NUM_THREADS="1")
        proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
        if proc.returncode:
            raise RuntimeError(proc.stderr[-2000:])
        out = json.loads(res.read_text())
    print(f"DEM phase of a coupled FE step ({out['particles']} particles, {out['substeps']} "
          f"substeps, 1 rank, 1 thread, {out['cpu_model']}):")
    for clock in ("wall", "cpu"):
        t = out[clock]
        print(f"  {clock}: median {t['coupled_dem_phase']['median_s'] * 1e3:.1f} ms (min "
              f"{t['coupled_dem_phase']['min_s'] * 1e3:.1f}) vs one sim.step({out['substeps']})"
              f" {t['plain_step']['median_s'] * 1e3:.1f} ms (min "
              f"{t['plain_step']['min_s'] * 1e3:.1f}): ratio "
              f"{out[f'ratio_{clock}_median']:.3f} (of the mins {out[f'ratio_{clock}_min']:.3f});"
              f" the per-step Python loop before: "
              f"{t['python_loop_before']['median_s'] * 1e3:.1f} ms "
              f"({out[f'ratio_python_loop_{clock}_median']:.2f}x)", flush=True)
    return out


if args.dem_phase_worker is not None:
    dem_phase_worker(args.dem_phase_worker)
    sys.exit(0)
dem = dem_phase() if "dem_phase" in args.parts else None
if "punch" not in args.parts:
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps({"dem_phase": dem}, indent=2))
    print(f"wrote {args.out / 'results.json'}")
    sys.exit(0)


def run(handshake, ranks):
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "demos/2d/coupled_punch.py", "--handshake", str(handshake), "--out", tmp]
        if ranks > 1:
            cmd = [str(Path(sys.executable).parent / "mpiexec"), "-n", str(ranks)] + cmd
        env = dict(os.environ, NUMBA_NUM_THREADS="1")
        proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
        if proc.returncode:
            raise RuntimeError(proc.stderr[-2000:])
        return json.loads((Path(tmp) / "results.json").read_text())


rows = []
for ranks in args.ranks:
    for hs in args.handshakes:
        reps = [run(hs, ranks) for _ in range(args.repeat)]
        for k, c in enumerate(reps[0]["coupled"]):
            times = [r["coupled"][k]["time_s"] for r in reps]
            parts = {key: [r["coupled"][k]["timings"][key] for r in reps]
                     for key in ("fe", "particles", "projection", "operators")}
            coupling = [p + o for p, o in zip(parts["projection"], parts["operators"], strict=False)]
            rows.append({
                "ranks": ranks, "handshake_elements": hs, "window_half_width": c["window_half_width"],
                "grains": c["grains"], "iterations": c["iterations"],
                "error_vs_full_dem": c["error_vs_full_dem"],
                "fe_only_error": c["fe_only_error_same_grains"],
                "time_min": min(times), "time_median": float(np.median(times)),
                **{f"time_{key}_median": float(np.median(v)) for key, v in parts.items()},
                "coupling_share_median": float(np.median(np.array(coupling) / np.array(times))),
                "full_dem_time_median": float(np.median([r["full_dem"]["time_s"] for r in reps])),
                "full_dem_grains": reps[0]["full_dem"]["grains"],
            })
            print(f"ranks {ranks} overlap {hs:.0f} h, window {c['window_half_width']:.2f} m: "
                  f"{rows[-1]['time_median']:.2f} s, error {c['error_vs_full_dem']:.2e}, "
                  f"coupling share {rows[-1]['coupling_share_median']:.1%}", flush=True)

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

args.out.mkdir(parents=True, exist_ok=True)
(args.out / "results.json").write_text(json.dumps({"repeat": args.repeat, "short": SHORT, "points": rows,
                                                   "note": "times are wall times of the coupled solve "
                                                           "(set-up included); shares are of that time",
                                                   "dem_phase": dem},
                                                  indent=2))
fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
for ranks in args.ranks:
    for hs in args.handshakes:
        s = [r for r in rows if r["ranks"] == ranks and r["handshake_elements"] == hs]
        axes[0].loglog([r["time_median"] for r in s], [r["error_vs_full_dem"] for r in s], "o-",
                       label=f"overlap {hs:.0f} h, {ranks} rank(s)")
axes[0].axhline(rows[0]["fe_only_error"], color="k", ls="--", label="FE only")
axes[0].set_xlabel("coupled run time [s] (median)")
axes[0].set_ylabel("error of window grains vs full DEM")
axes[0].legend(fontsize=8)
s = [r for r in rows if r["ranks"] == args.ranks[0] and r["handshake_elements"] == args.handshakes[0]]
labels = [f"{r['window_half_width']:.2f}" for r in s]
bottom = np.zeros(len(s))
for key in ("fe", "particles", "projection", "operators"):
    v = np.array([r[f"time_{key}_median"] for r in s])
    axes[1].bar(labels, v, bottom=bottom, label=key)
    bottom += v
axes[1].set_xlabel("window half-width [m]")
axes[1].set_ylabel("time [s]")
axes[1].set_title("time split of a coupled solve")
axes[1].legend()
fig.tight_layout()
fig.savefig(args.out / "coupling_cost.png", dpi=120)
print(f"wrote {args.out / 'results.json'}")
