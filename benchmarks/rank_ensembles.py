"""Serial and 2-rank coupled penetrations as ensembles of packings, and run-to-run identity.

A coupled run with grains is chaotic: round-off of a different rank count (another assembly
and reduction order) grows about tenfold per FE step into another trajectory, as another
packing would. So runs on 1 and 2 ranks are compared the way packings are: as ensembles.
For each rank count the 2D penetration scene (reduced: short settle, 2 cm push) runs on
``--seeds`` packings; per run the mean q_c over the last half of the push; per ensemble
their mean, the scatter of one packing and the standard error of the mean. The ensembles
agree when their means differ by less than about two combined standard errors. Each rank
count's first packing also runs a second time: the same bits run to run is asserted (the
continuum's redundant sequential MUMPS, :data:`granfe.solvers.REDUNDANT`).

Writes ``results.json``. Run: ``python benchmarks/rank_ensembles.py`` (about 10 minutes on
2 cores; each run is launched with ``mpiexec -n <ranks> granfe run``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from machine import cpu_model

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
SHORT = os.environ.get("GRANFE_SHORT") == "1"
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--out", type=Path, default=Path("output/rank_ensembles"))
parser.add_argument("--seeds", type=int, default=2 if SHORT else 5)
parser.add_argument("--depth", type=float, default=0.006 if SHORT else 0.02)
parser.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
args = parser.parse_args()

SETS = ["--set", f"penetrator.depth={args.depth}", "--set", "grains.settle_time=0.05", "--set", "output.png=false",
        "--set", "output.fields=false", "--set", "output.particles=false", "--set", "output.checkpoint_every=0"]


def run(ranks: int, seed: int) -> dict:
    """One ``granfe run`` of the scene; its q_c history and wall time."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [str(BIN / "mpiexec"), "-n", str(ranks), str(BIN / "granfe"), "run", "scenes/cpt_2d.toml",
               "--no-progress", "--out", tmp, "--overwrite", "--set", f"grains.seed={seed}", *SETS]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True,
                              env={**os.environ, "NUMBA_NUM_THREADS": "1"})
        if proc.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
        history = json.loads((Path(tmp) / "results.json").read_text())["history"]
    q = np.array([h["q_c"] for h in history])
    return {"seed": seed, "ranks": ranks, "wall_time_s": time.perf_counter() - t0,
            "q_c_mean_last_half": float(q[len(q) // 2:].mean()), "q_c": q.tolist()}




ensembles, identical = {}, {}
for ranks in args.ranks:
    runs = [run(ranks, seed) for seed in range(1, args.seeds + 1)]
    again = run(ranks, 1)
    identical[ranks] = again["q_c"] == runs[0]["q_c"]
    means = np.array([r["q_c_mean_last_half"] for r in runs])
    ensembles[ranks] = {"runs": runs, "mean": float(means.mean()), "scatter": float(means.std(ddof=1)),
                        "standard_error": float(means.std(ddof=1) / np.sqrt(len(means))),
                        "repeat_bit_identical": identical[ranks]}
    print(f"{ranks} rank(s): mean q_c over the last half {means.mean():.0f} Pa, one packing's scatter "
          f"{means.std(ddof=1):.0f} Pa, standard error {ensembles[ranks]['standard_error']:.0f} Pa; "
          f"repeat bit-identical: {identical[ranks]}", flush=True)

a, b = (ensembles[r] for r in args.ranks[:2])
combined = float(np.hypot(a["standard_error"], b["standard_error"]))
summary = {"difference_of_means": b["mean"] - a["mean"], "combined_standard_error": combined,
           "within_two_standard_errors": abs(b["mean"] - a["mean"]) <= 2 * combined}
print(f"2 ranks - 1 rank: {summary['difference_of_means']:.0f} Pa against a combined standard error "
      f"{combined:.0f} Pa", flush=True)
args.out.mkdir(parents=True, exist_ok=True)
(args.out / "results.json").write_text(json.dumps(
    {"inputs": {"scene": "scenes/cpt_2d.toml", "sets": SETS, "seeds": args.seeds, "ranks": args.ranks},
     "cpu": cpu_model(), "ensembles": {str(k): v for k, v in ensembles.items()}, "summary": summary}, indent=1))
assert all(identical.values()), f"a repeated run differed: {identical}"
