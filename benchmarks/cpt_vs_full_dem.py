"""Coupled cone penetration against full DEM: tip-resistance error against run time, and the
strong scaling of the 3D coupled scene.

2D: the penetration scene at reduced size runs fully as DEM (grains fill the whole chamber,
walls around) and coupled with several DE-window sizes, each on ``--seeds`` packings (a
single packing's q_c is a noisy, chaotic signal: comparing one run with one run measures
mostly that noise). The error is the relative RMS difference of the seed-averaged tip
resistance q_c, smoothed over ``--smooth`` of depth, against the seed-averaged full DEM once
the cone is embedded, plus the difference of the mean q_c over the last half of the push.
The full DEM's own seed-to-seed scatter (one packing against the average) and the standard
error of its average are reported beside it: the floor below which an error means nothing.
Run times are mean wall times per run of set-up (settling) and push.

3D strong scaling: the reduced 3D coupled cone scene (a few thousand spheres) is run with
``mpiexec -n 1`` and ``-n 2`` (``NUMBA_NUM_THREADS=1``), each ``--scaling-repeats`` times,
and on 1 rank with 2 numba threads (the DEM threaded, the FE serial);
the figure is the wall time per FE step (min and median over the timed steps of all
repeats), with the DEM part of it (the grains are replicated on every rank, so across ranks
only the FE solve and the exchange can scale; across threads only the DEM).

Writes ``results.json`` and ``cpt_vs_full_dem.png`` (q_c curves, the error-time front, the
scaling line). ``--parts scaling`` runs only the 3D line and keeps the 2D entries of an
existing ``results.json`` in ``--out``.

Run: ``python benchmarks/cpt_vs_full_dem.py`` (about 5 minutes on 2 idle cores for 2D, a few
more for the scaling line).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np

from coupling.apps.penetration.coupled import CoupledPenetration, DemPenetration, PenetrationParameters

SHORT = os.environ.get("GRANFE_SHORT") == "1"
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--out", type=Path, default=Path("output/cpt_vs_full_dem"))
parser.add_argument("--windows", type=float, nargs="+", default=[0.03, 0.045] if SHORT else [0.03, 0.04, 0.06])
parser.add_argument("--depth", type=float, default=0.012 if SHORT else 0.03)
parser.add_argument("--smooth", type=float, default=0.005, help="smoothing length of q_c [m]")
parser.add_argument("--seeds", type=int, default=1 if SHORT else 3,
                    help="packings per configuration: errors are between seed-averaged curves")
parser.add_argument("--parts", choices=["all", "2d", "scaling"], default="all")
parser.add_argument("--ranks", type=int, nargs="+", default=[1, 2], help="rank counts of the 3D line")
parser.add_argument("--hybrid-threads", type=int, default=2,
                    help="also run 1 rank with this many numba threads (0: not)")
parser.add_argument("--scaling-steps", type=int, default=4 if SHORT else 12, help="FE steps timed per run")
parser.add_argument("--scaling-repeats", type=int, default=1 if SHORT else 2)
parser.add_argument("--scaling-worker", type=Path, default=None, help=argparse.SUPPRESS)
args = parser.parse_args()
comm = MPI.COMM_WORLD
log = (lambda m: print(m, flush=True)) if comm.rank == 0 else (lambda m: None)

base = dict(chamber_width=0.2, chamber_depth=0.12, radius=2e-3, depth=args.depth, velocity=0.2,
            settle_time=0.1 if SHORT else 0.3, element_size_window=0.008, element_size_far=0.03)
# the reduced 3D scene of the scaling line (scenes/cpt_3d.toml at ~1/4 of its grains)
scaling = dict(dim=3, chamber_width=0.2, chamber_depth=0.12, window_half_width=0.025,
               window_depth=0.045, ghost_width=1.5, handshake=1.5, radius=2.5e-3, cone_radius=0.008,
               depth=0.02, velocity=0.4, settle_time=0.05, substeps=20,
               element_size_window=0.005 if not SHORT else 0.008, element_size_far=0.03)


def scaling_worker(path: Path) -> None:
    """One run of the 3D line under the current communicator: per-step wall times to ``path``."""
    t0 = time.perf_counter()
    model = CoupledPenetration(PenetrationParameters(**scaling), comm, log=lambda m: None)
    setup = time.perf_counter() - t0
    comm.barrier()
    # the first step factorises the FE matrix and the projection: time the steps after it
    history = model.run(steps=args.scaling_steps + 1)[1:]
    if comm.rank == 0:
        V = model.problem.V
        path.write_text(json.dumps({
            "ranks": comm.size, "grains": model.n_grains, "penetrator_spheres": len(model.pen_index),
            "dofs": V.dofmap.index_map.size_global * V.dofmap.index_map_bs, "setup_s": setup,
            "step_s": [h["wall_time"] for h in history], "dem_s": [h["dem_time"] for h in history],
            "q_c": [h["q_c"] for h in history], "load_average_1min": os.getloadavg()[0],
            "split_s": model.step_timings[1:]}))


def scaling_line() -> list[dict]:
    """Launch the workers (serially: one rank count at a time) and summarise them. Each rank
    holds all grains; the hybrid point (1 rank, numba threads for the DEM, a serial FE
    solve) is the other way to use two cores."""
    mpiexec = Path(sys.executable).parent / "mpiexec"
    points = []
    configs = [(ranks, 1) for ranks in args.ranks]
    if args.hybrid_threads > 1:
        configs.append((1, args.hybrid_threads))
    for ranks, threads in configs:
        runs = []
        for repeat in range(args.scaling_repeats):
            path = args.out / f"scaling_n{ranks}_t{threads}_r{repeat}.json"
            cmd = [str(mpiexec), "-n", str(ranks), sys.executable, __file__, "--scaling-worker", str(path),
                   "--scaling-steps", str(args.scaling_steps)]
            proc = subprocess.run(cmd, capture_output=True, text=True,
                                  env={**os.environ, "NUMBA_NUM_THREADS": str(threads)})
            if proc.returncode:
                raise RuntimeError(f"scaling run on {ranks} ranks failed:\n{proc.stderr[-3000:]}")
            runs.append(json.loads(path.read_text()))
        step = np.concatenate([r["step_s"] for r in runs])
        dem = np.concatenate([r["dem_s"] for r in runs])
        points.append({"ranks": ranks, "numba_threads": threads, "grains": runs[0]["grains"],
                       "dofs": runs[0]["dofs"],
                       "penetrator_spheres": runs[0]["penetrator_spheres"],
                       "repeats": len(runs), "steps_per_repeat": args.scaling_steps,
                       "step_s_min": float(step.min()), "step_s_median": float(np.median(step)),
                       "dem_s_median": float(np.median(dem)),
                       "load_average_1min": [r["load_average_1min"] for r in runs],
                       "fe_and_exchange_s_median": float(np.median(step - dem)),
                       # per FE step on rank 0: ghost interpolation + allgather, DEM sub-steps,
                       # nodal projection (M^-1 solve), FE solve (+ generalized-alpha update)
                       "split_s_median": {part: float(np.median([t[part] for r in runs for t in r["split_s"]]))
                                          for part in runs[0]["split_s"][0]},
                       "setup_s": [r["setup_s"] for r in runs], "runs": runs})
        split = ", ".join(f"{k} {v:.4f}" for k, v in points[-1]["split_s_median"].items())
        log(f"3D, {ranks} rank(s) x {threads} thread(s): {runs[0]['grains']} grains, {runs[0]['dofs']} dofs, "
            "per FE step "
            f"min {step.min():.3f} s, median {np.median(step):.3f} s (DEM {np.median(dem):.3f} s; "
            f"medians: {split})")
    return points


def smoothed(history):
    depth = np.array([h["depth"] for h in history])
    qc = np.array([h["q_c"] for h in history])
    k = max(1, int(round(args.smooth / max(depth[1] - depth[0], 1e-12))))
    return depth, np.convolve(qc, np.ones(k) / k, mode="same")


def timed(factory):
    t0 = time.perf_counter()
    model = factory()
    t1 = time.perf_counter()
    history = model.run()
    return model, history, t1 - t0, time.perf_counter() - t1


def ensemble(make, seeds, grid=None):
    """Runs ``make(seed)`` for each seed. Returns the depth grid (``grid``, or the first
    run's depths), the smoothed q_c of each run on it, the mean q_c over the last half of
    each push, mean set-up and push times, the first run's grains and history."""
    curves, tails, setups, runs = [], [], [], []
    for seed in seeds:
        model, h, setup, run = timed(lambda seed=seed: make(seed))
        d, q = smoothed(h)
        if grid is None:
            grid = d
        curves.append(np.interp(grid, d, q))
        tails.append(float(np.mean([x["q_c"] for x in h[len(h) // 2:]])))
        setups.append(setup)
        runs.append(run)
        if seed == seeds[0]:
            first = (model.n_grains, h)
    return (grid, np.array(curves), tails, float(np.mean(setups)), float(np.mean(runs)), *first)


def coupled_vs_full() -> dict:
    seeds = list(range(1, args.seeds + 1))
    full_prm = PenetrationParameters(**base, window_half_width=max(args.windows), window_depth=0.08)
    # every curve is interpolated onto the depths of the first full run
    grid, full_curves, full_tails, setup_full, run_full, n_full, h0 = ensemble(
        lambda sd: DemPenetration(replace(full_prm, seed=sd), log=log), seeds)
    q_ref = full_curves.mean(axis=0)
    # compare once the cone tip has gone a third of its height into the grains
    embedded = grid > full_prm.cone_radius / np.tan(np.radians(full_prm.apex_deg) / 2) / 3
    scale = np.sqrt(np.mean(q_ref[embedded] ** 2))

    def rms(q):
        return float(np.sqrt(np.mean((q[embedded] - q_ref[embedded]) ** 2)) / scale)

    scatter = float(np.mean([rms(q) for q in full_curves])) if len(seeds) > 1 else float("nan")
    std_error = (float(np.sqrt(np.mean(full_curves[:, embedded].var(axis=0, ddof=1)) / len(seeds)) / scale)
                 if len(seeds) > 1 else float("nan"))
    log(f"full DEM: {n_full} grains, {len(seeds)} packings, set-up {setup_full:.1f} s, push "
        f"{run_full:.1f} s per run; one packing against the average: {scatter:.1%} RMS, standard "
        f"error of the average {std_error:.1%}")
    points = []
    for a in args.windows:
        prm = PenetrationParameters(**base, window_half_width=a, window_depth=min(0.08, 0.11))
        _, curves, tails, setup, run, grains, _ = ensemble(
            lambda sd, prm=prm: CoupledPenetration(replace(prm, seed=sd), comm, log=log), seeds, grid)
        q = np.mean(curves, axis=0)
        err = rms(q)
        mean_err = float(abs(np.mean(tails) - np.mean(full_tails)) / abs(np.mean(full_tails)))
        points.append({"window_half_width": a, "grains": grains, "setup_s": setup, "run_s": run,
                       "total_s": setup + run, "q_c_rms_error": err, "q_c_mean_error_last_half": mean_err,
                       "q_c_rms_error_per_packing": [rms(c) for c in curves],
                       "q_c_mean": q.tolist()})
        log(f"window {a:.3f} m: {grains} grains, set-up {setup:.1f} s, push {run:.1f} s per run, "
            f"seed-averaged q_c RMS error {err:.1%}, mean q_c error {mean_err:.1%}")
    return {"parameters": base, "seeds": seeds, "depth": grid.tolist(),
            "full_dem": {"grains": n_full, "setup_s": setup_full, "run_s": run_full,
                         "total_s": setup_full + run_full, "q_c_mean": q_ref.tolist(),
                         "q_c_std": full_curves.std(axis=0).tolist(),
                         "one_packing_rms_vs_average": scatter, "standard_error_of_average": std_error,
                         "history": h0},
            "coupled": points}


def plot(results: dict) -> None:
    import matplotlib.pyplot as plt

    have_2d = "full_dem" in results
    line = results.get("scaling_3d")
    panels = (2 if have_2d else 0) + (1 if line else 0)
    fig, axes = plt.subplots(1, panels, figsize=(5.4 * panels, 4.5), squeeze=False)
    axes = axes[0]
    if have_2d:
        full = results["full_dem"]
        d_ref, q_ref, q_std = (np.array(results["depth"]), np.array(full["q_c_mean"]),
                               np.array(full["q_c_std"]))
        n = len(results["seeds"])
        axes[0].fill_betweenx(d_ref * 100, (q_ref - q_std) / 1e3, (q_ref + q_std) / 1e3, color="0.8",
                              label="full DEM, +- 1 std over packings")
        axes[0].plot(q_ref / 1e3, d_ref * 100, "k", lw=2, label=f"full DEM ({full['grains']} grains)")
        for p in results["coupled"]:
            axes[0].plot(np.array(p["q_c_mean"]) / 1e3, d_ref * 100,
                         label=f"coupled, window {p['window_half_width'] * 100:.0f} cm ({p['grains']} grains)")
        axes[0].invert_yaxis()
        axes[0].set_xlabel("q_c, smoothed [kPa]")
        axes[0].set_ylabel("depth [cm]")
        axes[0].legend(fontsize=8)
        axes[0].set_title(f"2D, q_c averaged over {n} packings")
        pts = results["coupled"]
        axes[1].loglog([p["total_s"] for p in pts], [p["q_c_rms_error"] for p in pts], "o-",
                       label="coupled (seed-averaged)")
        axes[1].axvline(full["total_s"], color="k", ls="--", label="full DEM run time")
        if n > 1:
            axes[1].axhline(full["one_packing_rms_vs_average"], color="0.5", ls=":",
                            label="full DEM: one packing vs average")
            axes[1].axhline(full["standard_error_of_average"], color="0.5", ls="-.",
                            label="full DEM: standard error of the average")
        axes[1].set_xlabel("run time per packing [s] (settling + push)")
        axes[1].set_ylabel("relative RMS error of q_c")
        axes[1].legend(fontsize=8)
        axes[1].set_title("2D")
    if line:
        ax = axes[-1]
        pts = [p for p in line["points"] if p.get("numba_threads", 1) == 1]
        ranks = np.array([p["ranks"] for p in pts])
        med = np.array([p["step_s_median"] for p in pts])
        ax.plot(ranks, med, "o-", label="wall time per FE step (median)")
        ax.plot(ranks, [p["step_s_min"] for p in pts], "s--", label="min")
        ax.plot(ranks, [p["dem_s_median"] for p in pts], "^:", label="DEM part (median)")
        ax.plot(ranks, med[0] / ranks * ranks[0], "k", lw=0.8, label="ideal")
        for p in line["points"]:
            if p.get("numba_threads", 1) > 1:
                cores = p["ranks"] * p["numba_threads"]
                ax.plot([cores], [p["step_s_median"]], "D", color="C3",
                        label=f"{p['ranks']} rank x {p['numba_threads']} threads (median)")
                ax.plot([cores], [p["dem_s_median"]], "v", color="C3",
                        label=f"{p['ranks']} rank x {p['numba_threads']} threads, DEM part")
        ax.set_xticks(ranks)
        ax.set_xlabel("cores (MPI ranks x numba threads)")
        ax.set_ylabel("s per FE step")
        p0 = line["points"][0]
        ax.set_title(f"3D coupled, {p0['grains']} grains, {p0['dofs']} dofs")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "cpt_vs_full_dem.png", dpi=120)


if args.scaling_worker is not None:
    scaling_worker(args.scaling_worker)
    sys.exit(0)

if comm.rank == 0:
    args.out.mkdir(parents=True, exist_ok=True)
results_path = args.out / "results.json"
results = json.loads(results_path.read_text()) if (args.parts == "scaling" and results_path.exists()) else {}
if args.parts in ("all", "2d"):
    results.update(coupled_vs_full())
if args.parts in ("all", "scaling") and comm.rank == 0:
    results["scaling_3d"] = {"parameters": scaling, "points": scaling_line(),
                             "command": " ".join(sys.argv)}
if comm.rank == 0:
    inputs = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    results["inputs"] = inputs | {"short": SHORT, "mpi_ranks": comm.size}
    results_path.write_text(json.dumps(results, indent=2, default=float))
    plot(results)
    print(f"wrote {results_path}")
