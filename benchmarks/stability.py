"""Stability map of the coupled cone penetration.

Pushes the 2D penetration scene (reduced: short settle, 1.5 cm push) while one parameter at
a time departs from the default: cone velocity, DE sub-steps per FE step (the FE step),
the relaxation of the exchanged values, the overlap (handshake) width, the DEM time-step
factor (x the default step; 20 reaches the critical step of the linear law) and the
stiffness contrast (the continuum's constants x a factor against those derived from the
grains). Every sweep runs with both exchanges: ``loose`` (one relaxed pass per FE step) and
``iqn-ils`` (iterated within the FE step to ``interface_tol`` by interface quasi-Newton; the
mean and largest iteration counts are reported). Each run either finishes, or stops with
the message the user would see and its last good state written (``run_penetration``
catches the divergence). Writes ``results.json`` and a table ``stability.md``; also checks
that no finished run returned non-finite or absurd tip resistance (garbage instead of an
error).

Run: ``python benchmarks/stability.py [--interface loose iqn-ils]`` (about 40 minutes on 2
cores for both).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np

from coupling.apps.penetration.coupled import PenetrationParameters
from coupling.apps.penetration.run import run_penetration

SHORT = os.environ.get("GRANFE_SHORT") == "1"
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--out", type=Path, default=Path("output/stability"))
parser.add_argument("--interface", nargs="+", default=["loose", "iqn-ils"], choices=["loose", "iqn-ils"])
args = parser.parse_args()
comm = MPI.COMM_WORLD

base = dict(settle_time=0.08, depth=0.008 if SHORT else 0.015, chamber_width=0.2, chamber_depth=0.12,
            radius=2e-3, element_size_far=0.03)
# each sweep is pushed past where the run stops (defaults: velocity 0.2 m/s, 50 sub-steps,
# relaxation 0.3, handshake 2 elements, dt_factor 1 = 0.05 of the linear law's critical step,
# continuum_stiffness 1 = the constants derived from the grains)
SWEEPS = {
    "velocity": [0.2, 2.0] if SHORT else [0.1, 0.5, 1.0, 2.0, 3.0, 4.0, 8.0],
    "substeps": [50, 400] if SHORT else [2, 5, 10, 50, 200, 800],
    "relaxation": [0.3, 1.0] if SHORT else [0.1, 0.3, 0.6, 0.8, 1.0],
    "handshake": [1.0] if SHORT else [0.25, 0.5, 1.0, 2.0],
    "dt_factor": [4.0] if SHORT else [2.0, 5.0, 10.0, 15.0, 20.0, 25.0, 40.0],
    "continuum_stiffness": [10.0] if SHORT else [0.01, 0.1, 10.0, 100.0, 1000.0],
    "interface_tol": [1e-2] if SHORT else [1e-2, 1e-4],
}


def attempt(name, value, out, interface) -> dict:
    """One run with ``name = value``: finished (max q_c), stopped (its message and whether
    the last state was written) or refused before anything was computed."""
    try:
        prm = PenetrationParameters(**base, **{name: value}, interface=interface)
    except ValueError as err:
        return {"status": "refused", "message": str(err)[:300]}
    try:
        res = run_penetration(prm, out, comm, frames=1, fields=False, particles=False, png=False,
                              progress=False, log=lambda m: None)
    except RuntimeError as err:
        return {"status": "stopped", "message": str(err).split("; the ")[0][:300],
                "last_state_written": (Path(out) / "last_good").exists()}
    qc = np.array([h["q_c"] for h in res["history"]])
    sane = bool(np.all(np.isfinite(qc)) and np.abs(qc).max() < 1e7)
    its = [h.get("interface_iterations", 1) for h in res["history"]]
    return {"status": "finished" if sane else "GARBAGE", "max_q_c": float(np.abs(qc).max()),
            "message": "", "iterations_mean": float(np.mean(its)), "iterations_max": int(np.max(its)),
            "steps_not_converged": sum(not h.get("interface_converged", True) for h in res["history"])}


rows = []
for interface in args.interface:
    for name, values in SWEEPS.items():
        if name == "interface_tol" and interface == "loose":
            continue
        for value in values:
            t0 = time.perf_counter()
            with tempfile.TemporaryDirectory() as tmp:
                row = {"interface": interface, "parameter": name, "value": value,
                       **attempt(name, value, comm.bcast(tmp, root=0), interface)}
            row["time_s"] = time.perf_counter() - t0
            rows.append(row)
            if comm.rank == 0:
                print(f"{interface}: {name} = {value}: {row['status']} ({row['time_s']:.0f} s, "
                      f"{row.get('iterations_mean', float('nan')):.1f} it/step) {row['message'][:120]}", flush=True)

if comm.rank == 0:
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps({"base": base, "short": SHORT, "runs": rows}, indent=2))
    lines = ["| exchange | parameter | value | outcome | max q_c [kPa] | iterations mean / max | time [s] | message |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {r['interface']} | {r['parameter']} | {r['value']} | {r['status']} | "
              f"{r['max_q_c'] / 1e3 if 'max_q_c' in r else float('nan'):.3g} | "
              + (f"{r['iterations_mean']:.1f} / {r['iterations_max']}" if "iterations_mean" in r else "-")
              + f" | {r['time_s']:.1f} | {r['message'][:100]} |" for r in rows]
    # the stable region: the range of values that finished, per parameter (others at default)
    lines += ["", "| exchange | parameter | finished for | stopped or refused for |", "| --- | --- | --- | --- |"]
    for interface in args.interface:
        for name in SWEEPS:
            mine = [r for r in rows if r["parameter"] == name and r["interface"] == interface]
            if not mine:
                continue
            ok = [r["value"] for r in mine if r["status"] == "finished"]
            bad = [r["value"] for r in mine if r["status"] != "finished"]
            span = f"{min(ok):g} to {max(ok):g}" if ok else "none"
            lines.append(f"| {interface} | {name} | {span} | {', '.join(f'{v:g}' for v in bad) or 'none'} |")
    (args.out / "stability.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    assert not any(r["status"] == "GARBAGE" for r in rows), "a run returned garbage without an error"
    assert all(r.get("last_state_written", True) for r in rows), "a stopped run lost its last state"
