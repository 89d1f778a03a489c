"""The coupled 3D chamber on one and two ranks: what a second core buys.

The scene is ``scenes/chamber_3d.toml`` (the force-carrying exchange, the window's constants
probed in situ; window ``--window`` half width). Each case runs in a fresh process,
``NUMBA_NUM_THREADS=1``, ``--repeat`` times, interleaved (1 rank, 2 ranks, 1 rank, ...) so that
a busy spell of the machine hits all alike:

- ``serial``: one rank;
- ``replicated``: two ranks, the continuum split over them and every grain on both (the
  default, ``coupling.distribute_grains = false``);
- ``distributed``: two ranks, the push's grains split over them by space
  (``distribute_grains = true``: the consolidated window continued as a
  `dem.DistributedSimulation`; the consolidation and the probe still run on every rank).

``--integrator implicit explicit`` runs every case with each continuum integrator (the
scene's: ``continuum.integrator``); speed-ups are given against the first case of the same
integrator and against the first case of all.

Per case: set-up and push wall times, the push's split (DEM, ghosts, FE solve; for the
distributed DEM also its halo exchanges, waits included, and its decompositions), and q_c
against the serial run's (the runs are different trajectories of a chaotic packing once
round-off differs, so they agree as packings do, not to the bit). Writes
``benchmarks/results/coupled_ranks.json`` (min and median over repeats, the CPU model).

Run: ``python benchmarks/coupled_ranks.py [--repeat 2] [--window 0.02] [--integrator implicit explicit]``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from machine import machine

ROOT = Path(__file__).resolve().parents[1]
SHORT = os.environ.get("GRANFE_SHORT") == "1"
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--scene", type=Path, default=ROOT / "scenes" / "chamber_3d.toml")
parser.add_argument("--window", type=float, default=0.02, help="window half width [m]")
parser.add_argument("--depth", type=float, default=None, help="push [m] (default the scene's)")
parser.add_argument("--repeat", type=int, default=1 if SHORT else 2)
parser.add_argument("--integrator", nargs="+", choices=["implicit", "explicit"], default=[None],
                    help="the continuum's time integrators, each with every case (default the scene's)")
parser.add_argument("--cases", nargs="+", default=["serial", "replicated", "distributed"],
                    choices=["serial", "replicated", "distributed"])
parser.add_argument("--out", type=Path, default=Path("output/coupled_ranks"))
parser.add_argument("--results", type=Path, default=ROOT / "benchmarks" / "results")
parser.add_argument("--worker", type=Path, default=None, help=argparse.SUPPRESS)
args = parser.parse_args()

RANKS = {"serial": 1, "replicated": 2, "distributed": 2}


def worker(path: Path) -> None:
    """One run (under mpiexec for two ranks): set-up, push, the timings on rank 0."""
    import dolfinx_solver  # noqa: F401
    from mpi4py import MPI

    from coupling.apps.penetration.coupled import CoupledPenetration
    from coupling.scene import load_scene

    case = json.loads(path.read_text())
    comm = MPI.COMM_WORLD
    overrides = {"window": {"half_width": case["window"]}, "coupling": {"distribute_grains": case["distribute"]}}
    if case["depth"] is not None:
        overrides["penetrator"] = {"depth": case["depth"]}
    if case["integrator"] is not None:
        overrides["continuum"] = {"integrator": case["integrator"]}
    prm = load_scene(case["scene"], overrides).parameters()
    comm.barrier()
    t0, c0 = time.perf_counter(), time.process_time()
    model = CoupledPenetration(prm, comm, log=lambda m: None)
    comm.barrier()
    t1, c1 = time.perf_counter(), time.process_time()
    history = model.run()
    comm.barrier()
    t2, c2 = time.perf_counter(), time.process_time()
    split = {k: float(sum(s.get(k, 0.0) for s in model.step_timings))
             for k in ("dem", "ghost_motion", "projection", "fe_solve", "total")}
    cpu = comm.allreduce(np.array([c1 - c0, c2 - c1]))
    # the distributed DEM's own split, rank 0's: halo exchanges (their waits for the other
    # rank included) and decompositions; the rest of its DEM time is its local stepping
    par = getattr(model.sim, "timings", None)
    if par is not None:
        par = {**par, "decompositions": int(model.sim.decompositions)}
    if comm.rank == 0:
        out = {"ranks": comm.size, "distributed": model.distributed, "grains": model.n_grains,
               "fe_steps": len(history), "dem_steps": int(model.sim.nsteps),
               "setup_s": t1 - t0, "push_s": t2 - t1, "setup_cpu_s": float(cpu[0]),
               "push_cpu_s": float(cpu[1]), "split_s": split, "dem_parallel": par,
               "q_c": [h["q_c"] for h in history], "depth": [h["depth"] for h in history]}
        path.with_suffix(".out.json").write_text(json.dumps(out))


def label(name: str, integrator: str | None) -> str:
    return name if integrator is None else f"{name}, {integrator}"


def run(name: str, integrator: str | None, k: int) -> dict:
    case = {"scene": str(args.scene), "window": args.window, "depth": args.depth,
            "integrator": integrator, "distribute": name == "distributed"}
    path = args.out / f"{name}_{integrator}_{k}.json"
    path.write_text(json.dumps(case))
    launch = [sys.executable, __file__, "--worker", str(path)]
    if RANKS[name] > 1:
        launch = [str(Path(sys.executable).parent / "mpiexec"), "-n", str(RANKS[name])] + launch
    proc = subprocess.run(launch, capture_output=True, text=True,
                          env={**os.environ, "NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"})
    if proc.returncode:
        raise RuntimeError(f"{name} failed:\n{proc.stderr[-3000:]}")
    out = json.loads(path.with_suffix(".out.json").read_text())
    print(f"{label(name, integrator)} ({k + 1}/{args.repeat}): set-up {out['setup_s']:.1f} s, "
          f"push {out['push_s']:.1f} s "
          f"(DEM {out['split_s']['dem']:.1f} s, FE {out['split_s']['fe_solve']:.1f} s)", flush=True)
    return out


def stats(values) -> dict:
    return {"min": float(np.min(values)), "median": float(np.median(values)), "all": [float(v) for v in values]}


if __name__ == "__main__":
    if args.worker is not None:
        worker(args.worker)
        sys.exit(0)
    args.out.mkdir(parents=True, exist_ok=True)
    args.results.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    pairs = [(name, integrator) for integrator in args.integrator for name in args.cases]
    runs = {label(*pair): [] for pair in pairs}
    for k in range(args.repeat):
        for pair in pairs:
            runs[label(*pair)].append(run(*pair, k))
    summary = {}
    first = label(*pairs[0])
    ref = np.array(runs[first][0]["q_c"])
    for (name, integrator), (key, rs) in zip(pairs, runs.items(), strict=True):
        push, setup = [r["push_s"] for r in rs], [r["setup_s"] for r in rs]
        summary[key] = {
            "ranks": RANKS[name], "integrator": integrator or "the scene's",
            "grains": rs[0]["grains"], "fe_steps": rs[0]["fe_steps"],
            "setup_s": stats(setup), "push_s": stats(push), "total_s": stats(np.add(setup, push)),
            "push_dem_s": stats([r["split_s"]["dem"] for r in rs]),
            "push_fe_s": stats([r["split_s"]["fe_solve"] for r in rs]),
            "push_cpu_s": stats([r["push_cpu_s"] for r in rs]),
            "dem_parallel": [r["dem_parallel"] for r in rs],
            # q_c against the first case's first run over the push (RMS over its largest value)
            "q_c_rms_vs_first": [float(np.sqrt(np.mean((np.array(r["q_c"]) - ref) ** 2)) / np.abs(ref).max())
                                 for r in rs]}
    for (_, integrator), (key, s) in zip(pairs, summary.items(), strict=True):
        # against the first case of the same integrator (what more ranks buy), and against
        # the first case of all
        for tag, base in (("", summary[label(args.cases[0], integrator)]), ("_vs_first", summary[first])):
            for k in ("push_s", "total_s"):
                s[f"speedup_{k[:-2]}_median{tag}"] = base[k]["median"] / s[k]["median"]
                s[f"speedup_{k[:-2]}_min{tag}"] = base[k]["min"] / s[k]["min"]
        print(f"{key}: push {s['push_s']['median']:.1f} s median ({s['speedup_push_median']:.2f}x; "
              f"{s['speedup_push_median_vs_first']:.2f}x {first}), total {s['total_s']['median']:.1f} s "
              f"({s['speedup_total_median']:.2f}x), q_c RMS against {first}: "
              f"{', '.join(f'{e:.3f}' for e in s['q_c_rms_vs_first'])}")
    results = {"command": " ".join(sys.argv), "inputs": {k: str(v) for k, v in vars(args).items()},
               "machine": machine(), "wall_time_s": time.perf_counter() - t0,
               "load_average_at_end": os.getloadavg(), "cases": summary}
    path = args.results / "coupled_ranks.json"
    if path.exists():   # the file's earlier runs are kept, the last one among them
        old = json.loads(path.read_text())
        earlier = old.pop("earlier", {})
        earlier[f"before {time.strftime('%Y-%m-%d %H:%M')}"] = old
        results["earlier"] = earlier
    path.write_text(json.dumps(results, indent=1))
    print(f"wrote {path}")
