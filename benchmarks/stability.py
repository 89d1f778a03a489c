"""Stability map of the coupled cone penetration.

Pushes the 2D penetration scene (reduced: short settle, 1.5 cm push) while one parameter at
a time departs from the default: cone velocity, contact stiffness (the grains' stiffness
against the continuum derived from them is kept consistent, so this is a time-scale
contrast), DE sub-steps per FE step (the FE step), the relaxation of the exchanged values,
and the overlap width. Each run either finishes, or stops with the message the user would
see and its last good state written (``run_penetration`` catches the divergence). Writes
``results.json`` and a table ``stability.md``; also checks that no finished run returned
non-finite or absurd tip resistance (garbage instead of an error).

Run: ``python benchmarks/stability.py`` (about 10 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401

import numpy as np
from mpi4py import MPI

from coupling.penetration import PenetrationParameters
from coupling.penetration_run import run_penetration

SHORT = os.environ.get("GRANFE_SHORT") == "1"
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--out", type=Path, default=Path("output/stability"))
args = parser.parse_args()
comm = MPI.COMM_WORLD

base = dict(settle_time=0.08, depth=0.008 if SHORT else 0.015, chamber_width=0.2, chamber_depth=0.12,
            radius=2e-3, element_size_far=0.03)
SWEEPS = {
    "velocity": [0.2, 2.0] if SHORT else [0.1, 0.5, 2.0, 8.0],
    "substeps": [50, 400] if SHORT else [10, 50, 200, 800],
    "relaxation": [0.3, 1.0] if SHORT else [0.1, 0.3, 0.6, 1.0],
    "handshake": [1.0] if SHORT else [0.5, 1.0, 2.0],
}
rows = []
for name, values in SWEEPS.items():
    for value in values:
        prm = PenetrationParameters(**base, **{name: value})
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            out = comm.bcast(tmp, root=0)
            try:
                res = run_penetration(prm, out, comm, frames=1, fields=False, particles=False, png=False,
                                      progress=False, log=lambda m: None)
                qc = np.array([h["q_c"] for h in res["history"]])
                sane = bool(np.all(np.isfinite(qc)) and np.abs(qc).max() < 1e7)
                row = {"parameter": name, "value": value, "status": "finished" if sane else "GARBAGE",
                       "max_q_c": float(np.abs(qc).max()), "message": ""}
            except RuntimeError as err:
                last = Path(out) / "last_good"
                row = {"parameter": name, "value": value, "status": "stopped",
                       "message": str(err).split("; the last state")[0][:300],
                       "last_state_written": last.exists()}
        row["time_s"] = time.perf_counter() - t0
        rows.append(row)
        if comm.rank == 0:
            print(f"{name} = {value}: {row['status']} ({row['time_s']:.0f} s) {row['message'][:120]}", flush=True)

if comm.rank == 0:
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps({"base": base, "short": SHORT, "runs": rows}, indent=2))
    lines = ["| parameter | value | outcome | message |", "| --- | --- | --- | --- |"]
    lines += [f"| {r['parameter']} | {r['value']} | {r['status']} | {r['message'][:100]} |" for r in rows]
    (args.out / "stability.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    assert not any(r["status"] == "GARBAGE" for r in rows), "a run returned garbage without an error"
    assert all(r.get("last_state_written", True) for r in rows), "a stopped run lost its last state"
