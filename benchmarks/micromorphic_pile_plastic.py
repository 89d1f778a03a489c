"""The plastic micromorphic continuum in the reduced pile (`scenes/pile_3d_micromorphic.toml`,
the scene of demos/3d/micromorphic_pile.py's elastic figures): q_c against depth, the count of
yielded quadrature points (macro level), the CPU time and the continuum solve's iterations of
every FE step (the elastic-Jacobian quasi-Newton's, or with ``fallback`` Newton's after it
failed), one packing.

Run (one core): ``NUMBA_NUM_THREADS=1 python benchmarks/micromorphic_pile_plastic.py
[--cohesion 800] [--set section.key=value ...]``; writes
``benchmarks/results/micromorphic_pile_plastic.json`` (``--results``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def plastic_points(cpt) -> dict:
    """Quadrature points whose macro level has yielded (equivalent plastic strain > 0) and the
    largest equivalent plastic strain (collective)."""
    comm = cpt.comm
    eq = cpt.problem.state.owned("equivalent_plastic_strain").reshape(-1, 5)[:, 0]
    return {"plastic_points": comm.allreduce(int((eq > 0).sum()), MPI.SUM),
            "points": comm.allreduce(int(eq.size), MPI.SUM),
            "max_equivalent_plastic_strain": comm.allreduce(float(eq.max(initial=0.0)), MPI.MAX)}


def main():
    from machine import machine

    from coupling.apps.penetration.coupled import CoupledPenetration
    from coupling.scene import load_scene, parse_overrides

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", type=Path, default=ROOT / "scenes" / "pile_3d_micromorphic.toml")
    parser.add_argument("--cohesion", type=float, default=800.0,
                        help="Pa; the scene's packing needs >= ~584 Pa (the geostatic state's cone)")
    parser.add_argument("--set", nargs="*", default=[], help="more scene overrides, section.key=value")
    parser.add_argument("--results", type=Path,
                        default=ROOT / "benchmarks" / "results" / "micromorphic_pile_plastic.json")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    sets = ["continuum.model=micromorphic_drucker_prager", f"continuum.cohesion={args.cohesion}", *args.set]
    prm = load_scene(args.scene, parse_overrides(sets)).parameters()

    def log(msg):
        if comm.rank == 0:
            print(msg, flush=True)

    c0, t0 = time.process_time(), time.perf_counter()
    cpt = CoupledPenetration(prm, comm, log=log)
    setup = {"cpu_s": time.process_time() - c0, "wall_s": time.perf_counter() - t0,
             **plastic_points(cpt)}
    log(f"set-up {setup['cpu_s']:.1f} s CPU, geostatic plastic points {setup['plastic_points']}")
    steps = []

    def write(complete: bool):
        # after every step: a run stopped by its time limit keeps the steps it made
        qc = np.array([s["q_c"] for s in steps])
        peak = int(qc.argmax())
        out = {"scene": str(args.scene.relative_to(ROOT)), "overrides": sets, "ranks": comm.size,
               "machine": machine(), "cohesion_Pa": args.cohesion, "complete": complete,
               "fe_steps": cpt.n_steps, "setup": setup,
               "summary": {"q_c_peak": float(qc[peak]), "depth_at_peak": steps[peak]["depth"],
                           "q_c_mean_last_half": float(qc[len(qc) // 2:].mean()),
                           "cpu_s_per_step_median": float(np.median([s["cpu_s"] for s in steps])),
                           "solver_iterations_median": float(np.median([s["solver"]["iterations"]
                                                                        for s in steps])),
                           "fallbacks": cpt.stepper.fallbacks,
                           "push_cpu_s": float(sum(s["cpu_s"] for s in steps))},
               "steps": steps}
        if comm.rank == 0:
            args.results.write_text(json.dumps(out, indent=1))

    while len(cpt.history) < cpt.n_steps:
        c1 = time.process_time()
        h = cpt.advance()
        steps.append({"step": h["step"], "depth": h["depth"], "q_c": h["q_c"],
                      "cpu_s": time.process_time() - c1, **plastic_points(cpt),
                      "solver": dict(cpt.stepper.last_solve)})
        log(f"step {h['step']}: depth {1e3 * h['depth']:.2f} mm q_c {h['q_c'] / 1e3:.3f} kPa, "
            f"{steps[-1]['plastic_points']} plastic points, {steps[-1]['cpu_s']:.2f} s CPU, "
            f"solver {steps[-1]['solver']}")
        write(complete=len(cpt.history) == cpt.n_steps)
    log(f"wrote {args.results}")

if __name__ == "__main__":
    main()
