"""Cost of the DE x FE coupling: time split (FE, particles, projection, operators) and error
against run time as the DE window and the overlap width vary.

Runs ``demos/2d/coupled_punch.py`` (bonded grains under a rough punch, full DEM reference)
for each overlap width, ``--repeat`` times, in fresh processes; the demo's own timers split
each coupled solve into FE solves, particle solves, projections and operator set-up.
Writes ``results.json`` (min and median over repeats) and ``coupling_cost.png``.

Run: ``python benchmarks/coupling_cost.py [--ranks 1 2]``.
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

ROOT = Path(__file__).resolve().parents[1]
SHORT = os.environ.get("GRANFE_SHORT") == "1"
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--out", type=Path, default=Path("output/coupling_cost"))
parser.add_argument("--repeat", type=int, default=1 if SHORT else 3)
parser.add_argument("--handshakes", type=float, nargs="+", default=[1.0, 2.0] if SHORT else [1.0, 2.0, 3.0])
parser.add_argument("--ranks", type=int, nargs="+", default=[1] if SHORT else [1, 2])
args = parser.parse_args()


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
            coupling = [p + o for p, o in zip(parts["projection"], parts["operators"])]
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
                                                           "(set-up included); shares are of that time"},
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
