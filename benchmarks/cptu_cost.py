"""Cost and accuracy of the saturated coupled cone (CPTu) against its fluid step interval.

`demos/2d/cptu_coupled.py`'s partially drained push (``scenes/cptu_2d.toml``, V ~ 1, 45 mm)
in several packings (``--seeds``), each with a fluid step every ``--every`` DEM steps (1:
the fluid solved at every DEM step, its implicit group drag between; > 1: the DEM steps
between take the interval's linear response, `dem.response.LinearResponse` inside the
fused step loop), and dry in the same process as the first saturated case. Per case the
push's CPU time (the demo's ``time.process_time``, set-up apart), its ratio to the dry
push of the same packing, the fluid's own wall time, q_c and u2 averaged over the steady
part; per interval the mean over the packings, and with every = 1 among the cases, each
packing's q_c and u2 against it. A packing's q_c scatters by ~10 % from round-off alone
(a chaotic packing: one change of summation order moved packing 1 from 3.4 to 4.1 kPa), so
the intervals are compared over packings, not packing by packing. Every case is its own
process (one core: ``NUMBA_NUM_THREADS=1``). The CPU model and the load from
``benchmarks/machine.py``.

``--response-every``: DEM steps per application of the interval's forces (their impulse
once per block, `dem.response.LinearResponse`'s stride), each with every interval > 1.

Run: ``python benchmarks/cptu_cost.py`` (~4 min a packing with every = 1, ~1.5 min
without); ``--every 25 50`` for the intervals only; ``--every 25 --response-every 1 5``
for the stride against every DEM step.
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
from machine import machine

ROOT = Path(__file__).resolve().parents[1]
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3], help="packings")
parser.add_argument("--every", type=int, nargs="+", default=[1, 25, 50],
                    help="DEM steps per fluid step (1: the reference)")
parser.add_argument("--response-every", type=int, nargs="+", default=[5],
                    help="DEM steps per application of the interval's forces (with every > 1)")
parser.add_argument("--depth", type=float, default=0.045, help="push [m]")
parser.add_argument("--out", type=Path, default=Path("output/cptu_cost"))
args = parser.parse_args()


def demo(seed, every, stride, runs, out):
    """One process of the demo; returns its summary by run name."""
    env = dict(os.environ, NUMBA_NUM_THREADS="1")
    cmd = [sys.executable, str(ROOT / "demos/2d/cptu_coupled.py"), "--runs", *runs, "--seed",
           str(seed), "--every", str(every), "--response-every", str(stride), "--depth", str(args.depth),
           "--out", str(out)]
    subprocess.run(cmd, check=True, cwd=ROOT, env=env, stdout=subprocess.DEVNULL)
    return json.loads((out / "results.json").read_text())["summary"]


# (every, stride): the response's stride only where the DEM steps between take it
settings = [(every, stride) for every in args.every
            for stride in (args.response_every if every > 1 else [1]) if every % stride == 0]
cases = []
with tempfile.TemporaryDirectory() as tmp:
    for seed in args.seeds:
        dry = None
        for q, (every, stride) in enumerate(settings):
            s = demo(seed, every, stride, ["dry", "fast"] if q == 0 else ["fast"],
                     Path(tmp) / f"{seed}_{every}_{stride}")
            dry = s.get("dry", dry)
            fast = s["fast"]
            case = {"seed": seed, "every": every, "response_every": stride, "cpu_push_s": fast["cpu_push_s"],
                    "cpu_push_dry_s": dry["cpu_push_s"], "over_dry": fast["cpu_push_s"] / dry["cpu_push_s"],
                    "fluid_wall_s": fast["fluid_wall_s"], "q_c_kPa": fast["q_c_mean"] / 1e3,
                    "q_c_dry_kPa": dry["q_c_mean"] / 1e3, "u2_kPa": fast["u2_mean"] / 1e3, "V": fast["V"]}
            cases.append(case)
            print(f"seed {seed} every {every:3d} response_every {stride}: q_c {case['q_c_kPa']:.2f} kPa, "
                  f"u2 {case['u2_kPa']:.3f} kPa, push {case['cpu_push_s']:.1f} s CPU ({case['over_dry']:.2f}x dry)",
                  flush=True)

by_setting = {}
for every, stride in settings:
    rows = [c for c in cases if (c["every"], c["response_every"]) == (every, stride)]
    row = {k: float(np.mean([c[k] for c in rows])) for k in ("q_c_kPa", "u2_kPa", "over_dry", "cpu_push_s")}
    row["over_dry_min_median_max"] = [float(f(np.array([c["over_dry"] for c in rows])))
                                      for f in (np.min, np.median, np.max)]
    by_setting[f"every {every} response_every {stride}"] = row
if 1 in args.every:
    ref = by_setting["every 1 response_every 1"]
    for c in cases:
        one = next(r for r in cases if r["seed"] == c["seed"] and r["every"] == 1)
        c["q_c_vs_every_1"] = c["q_c_kPa"] / one["q_c_kPa"] - 1.0
        c["u2_minus_every_1_kPa"] = c["u2_kPa"] - one["u2_kPa"]
    for row in by_setting.values():
        row["q_c_mean_vs_every_1"] = row["q_c_kPa"] / ref["q_c_kPa"] - 1.0
for name, row in by_setting.items():
    print(f"{name}: q_c {row['q_c_kPa']:.2f} kPa, u2 {row['u2_kPa']:.3f} kPa, push "
          f"{row['over_dry']:.2f}x dry (min / median / max {row['over_dry_min_median_max']})")

args.out.mkdir(parents=True, exist_ok=True)
result = {"benchmark": "cptu_cost", "depth": args.depth, "machine": machine(), "cases": cases,
          "by_setting": by_setting}
(args.out / "results.json").write_text(json.dumps(result, indent=1))
print(f"written {args.out / 'results.json'}")
