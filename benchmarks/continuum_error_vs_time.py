"""Error against run time of the micropolar continuum solver (2D and 3D manufactured problems).

For each dimension, element pair (P1/P1, P2/P1, P2/P2), mesh size and linear solver
(direct MUMPS LU, or CG + GAMG with the rigid-body near-nullspace) it records dofs, L2
and H1 errors of u and phi, the assembly time of one Jacobian + residual, the SNES solve
time (which includes that assembly), and Krylov iterations. Every configuration runs
``--repeat`` times: min and median are stored. Writes ``results.json`` and a log-log plot.

Run: ``mpiexec -n 2 python benchmarks/continuum_error_vs_time.py [--budget 240]``.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import ufl
from dolfinx import fem, mesh
from dolfinx.fem.petsc import assemble_matrix, assemble_vector

from granfe.manufactured import errors, manufactured_problem

SHORT = os.environ.get("GRANFE_SHORT") == "1"
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--out", type=Path, default=Path("output/continuum_error_vs_time"))
parser.add_argument("--repeat", type=int, default=1 if SHORT else 3)
parser.add_argument("--max-solve", type=float, default=1.0 if SHORT else 12.0,
                    help="stop refining a series once one solve takes longer than this [s]")
parser.add_argument("--budget", type=float, default=60.0 if SHORT else 1200.0,
                    help="total time budget [s]; later series are skipped beyond it")
args = parser.parse_args()
comm = MPI.COMM_WORLD

SERIES = {
    3: {"sizes": [2, 4] if SHORT else [2, 4, 8, 12, 16, 24, 32], "solvers": ["iterative", "direct"]},
    2: {"sizes": [4, 8, 16] if SHORT else [8, 16, 32, 64, 128, 256], "solvers": ["direct"]},
}
PAIRS = [(1, 1), (2, 1), (2, 2)]


def make_mesh(gdim, n):
    if gdim == 2:
        return mesh.create_unit_square(comm, n, n)
    return mesh.create_unit_cube(comm, n, n, n)


def run(gdim, n, degree, solver):
    domain = make_mesh(gdim, n)
    times, assembly = [], []
    for r in range(args.repeat):
        problem, u_ex, phi_ex = manufactured_problem(domain, degree, solver=solver,
                                                     prefix=f"b{gdim}{n}{degree[0]}{degree[1]}{solver}{r}_")
        F = problem.residual()
        J = ufl.derivative(F, problem.w)
        Jf, Ff = fem.form(J), fem.form(F)
        comm.barrier()
        t0 = time.perf_counter()
        A = assemble_matrix(Jf, bcs=problem.bcs)
        A.assemble()
        b = assemble_vector(Ff)
        assembly.append(comm.allreduce(time.perf_counter() - t0, MPI.MAX))
        A.destroy(), b.destroy()
        comm.barrier()
        t0 = time.perf_counter()
        problem.solve()
        times.append(comm.allreduce(time.perf_counter() - t0, MPI.MAX))
    snes = problem.snes
    e = errors(problem, u_ex, phi_ex)
    imap = problem.V.dofmap.index_map
    return {
        "dim": gdim, "n": n, "degree": list(degree), "solver": solver,
        "dofs": imap.size_global * problem.V.dofmap.index_map_bs,
        **e,
        "time_assembly_min": min(assembly), "time_assembly_median": float(np.median(assembly)),
        "time_solve_min": min(times), "time_solve_median": float(np.median(times)),
        "snes_iterations": snes.getIterationNumber(),
        "krylov_iterations": snes.getLinearSolveIterations(),
    }


points = []
start = time.perf_counter()
for gdim, series in SERIES.items():
    for solver in series["solvers"]:
        for degree in PAIRS:
            for n in series["sizes"]:
                if time.perf_counter() - start > args.budget:
                    break
                p = run(gdim, n, degree, solver)
                points.append(p)
                if comm.rank == 0:
                    print(f"{gdim}D P{degree[0]}/P{degree[1]} {solver:9s} n={n:4d} dofs={p['dofs']:8d} "
                          f"u_L2={p['u_L2']:.2e} solve={p['time_solve_min']:.3f}s "
                          f"its={p['krylov_iterations']}", flush=True)
                if p["time_solve_min"] > args.max_solve:
                    break


def observed_rates(gdim, degree, solver, key):
    s = [p for p in points if p["dim"] == gdim and p["degree"] == list(degree) and p["solver"] == solver]
    return [float(np.log2(a[key] / b[key]) / np.log2(b["n"] / a["n"])) for a, b in zip(s, s[1:], strict=False)]


if comm.rank == 0:
    import matplotlib.pyplot as plt

    args.out.mkdir(parents=True, exist_ok=True)
    summary = {f"{g}D_P{d[0]}P{d[1]}_{s}": {k: observed_rates(g, d, s, k) for k in ("u_L2", "u_H1", "phi_L2")}
               for g in SERIES for s in SERIES[g]["solvers"] for d in PAIRS}
    results = {"ranks": comm.size, "repeat": args.repeat, "short": SHORT, "points": points,
               "observed_rates": summary,
               "note": "time_solve includes one residual+Jacobian assembly per Newton step "
                       "(linear problem: 1 step); times are max over ranks"}
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for ax, gdim in zip(axes, sorted(SERIES), strict=False):
        for solver in SERIES[gdim]["solvers"]:
            for degree in PAIRS:
                s = [p for p in points if p["dim"] == gdim and p["degree"] == list(degree)
                     and p["solver"] == solver]
                if s:
                    ax.loglog([p["time_solve_min"] for p in s], [p["u_L2"] for p in s],
                              "o-" if solver == "direct" else "s--",
                              label=f"P{degree[0]}/P{degree[1]} {solver}")
        ax.set_xlabel("solve time [s] (min of repeats)")
        ax.set_ylabel("L2 error of u")
        ax.set_title(f"{gdim}D manufactured solution, {comm.size} rank(s)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "error_vs_time.png", dpi=120)
    print(f"wrote {args.out / 'results.json'}")
