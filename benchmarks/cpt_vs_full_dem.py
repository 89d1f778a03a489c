"""Coupled cone penetration against full DEM: tip-resistance error against run time.

The 2D penetration scene at reduced size runs once fully as DEM (grains fill the whole
chamber, walls around) and coupled with several DE-window sizes. The error is the relative
RMS difference of the tip resistance q_c, smoothed over ``--smooth`` of depth, against the
full DEM once the cone is embedded, plus the difference of the mean q_c over the last half
of the push. Run times are wall times of set-up (settling) and push. Writes
``results.json`` and ``cpt_vs_full_dem.png`` (q_c curves and the error-time front).

Run: ``python benchmarks/cpt_vs_full_dem.py`` (about 5 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401

import numpy as np
from mpi4py import MPI

from coupling.penetration import CoupledPenetration, DemPenetration, PenetrationParameters

SHORT = os.environ.get("GRANFE_SHORT") == "1"
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--out", type=Path, default=Path("output/cpt_vs_full_dem"))
parser.add_argument("--windows", type=float, nargs="+", default=[0.03, 0.045] if SHORT else [0.03, 0.04, 0.06])
parser.add_argument("--depth", type=float, default=0.012 if SHORT else 0.03)
parser.add_argument("--smooth", type=float, default=0.005, help="smoothing length of q_c [m]")
args = parser.parse_args()
comm = MPI.COMM_WORLD
log = (lambda m: print(m, flush=True)) if comm.rank == 0 else (lambda m: None)

base = dict(chamber_width=0.2, chamber_depth=0.12, radius=2e-3, depth=args.depth, velocity=0.2,
            settle_time=0.1 if SHORT else 0.3, element_size_window=0.008, element_size_far=0.03)


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


full_prm = PenetrationParameters(**base, window_half_width=max(args.windows), window_depth=0.08)
full, h_full, setup_full, run_full = timed(lambda: DemPenetration(full_prm, log=log))
d_ref, q_ref = smoothed(h_full)
# compare once the cone tip has gone a third of its height into the grains
embedded = d_ref > full_prm.cone_radius / np.tan(np.radians(full_prm.apex_deg) / 2) / 3
log(f"full DEM: {full.n_grains} grains, set-up {setup_full:.1f} s, push {run_full:.1f} s")
points = []
for a in args.windows:
    prm = PenetrationParameters(**base, window_half_width=a, window_depth=min(0.08, 0.11))
    model, h, setup, run = timed(lambda: CoupledPenetration(prm, comm, log=log))
    d, q = smoothed(h)
    q_on_ref = np.interp(d_ref, d, q)
    scale = np.sqrt(np.mean(q_ref[embedded] ** 2))
    err = float(np.sqrt(np.mean((q_on_ref[embedded] - q_ref[embedded]) ** 2)) / scale)
    half = len(h) // 2
    mean_err = float(abs(np.mean([x["q_c"] for x in h[half:]]) - np.mean([x["q_c"] for x in h_full[half:]]))
                     / abs(np.mean([x["q_c"] for x in h_full[half:]])))
    points.append({"window_half_width": a, "grains": model.n_grains, "setup_s": setup, "run_s": run,
                   "total_s": setup + run, "q_c_rms_error": err, "q_c_mean_error_last_half": mean_err,
                   "history": h})
    log(f"window {a:.3f} m: {model.n_grains} grains, set-up {setup:.1f} s, push {run:.1f} s, "
        f"q_c RMS error {err:.1%}, mean q_c error {mean_err:.1%}")

if comm.rank == 0:
    import matplotlib.pyplot as plt

    args.out.mkdir(parents=True, exist_ok=True)
    results = {"inputs": vars(args) | {"out": str(args.out), "short": SHORT, "ranks": comm.size},
               "parameters": base,
               "full_dem": {"grains": full.n_grains, "setup_s": setup_full, "run_s": run_full,
                            "total_s": setup_full + run_full, "history": h_full},
               "coupled": points}
    (args.out / "results.json").write_text(json.dumps(results, indent=2, default=float))
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    axes[0].plot(q_ref / 1e3, d_ref * 100, "k", lw=2, label=f"full DEM ({full.n_grains} grains)")
    for p in points:
        d, q = smoothed(p["history"])
        axes[0].plot(q / 1e3, d * 100, label=f"coupled, window {p['window_half_width'] * 100:.0f} cm "
                                              f"({p['grains']} grains)")
    axes[0].invert_yaxis()
    axes[0].set_xlabel("q_c, smoothed [kPa]")
    axes[0].set_ylabel("depth [cm]")
    axes[0].legend(fontsize=8)
    axes[1].loglog([p["total_s"] for p in points], [p["q_c_rms_error"] for p in points], "o-", label="coupled")
    axes[1].axvline(setup_full + run_full, color="k", ls="--", label="full DEM run time")
    axes[1].set_xlabel("run time [s] (settling + push)")
    axes[1].set_ylabel("relative RMS error of q_c")
    axes[1].legend()
    fig.tight_layout()
    fig.savefig(args.out / "cpt_vs_full_dem.png", dpi=120)
    print(f"wrote {args.out / 'results.json'}")
