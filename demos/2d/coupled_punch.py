"""Coupled DE x FE against full DEM: a rough rigid punch pressed into a bonded granular block.

This demo shows how to:

- build a bonded hexagonal packing of disks (linear normal, tangential and rotational bonds)
  and its equivalent micropolar continuum (constants from the bond energy),
- solve the punch problem three ways: fully as DEM (every grain), fully as micropolar FE,
  and coupled: a DE window of grains under the punch inside the FE block, joined through
  an overlap (ghost particles follow the FE fields, FE nodes in the window follow the
  grains by the discrete L2 projection, seed 001 eq. 74-90), iterated by the staggered
  Schwarz loop with Aitken relaxation,
- measure the error of the window's grain displacements against the full DEM for several
  window sizes, with run times, and plot the displacement fields.

Run: ``mpiexec -n 2 python demos/2d/coupled_punch.py``.
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
from dolfinx import fem

from coupling.apps.punch.model import coupled_window, fe_block, lattice_block
from coupling.staggered import StaggeredOptions
from dem.bonded import BondedAssembly, BondedSubproblem, find_bonds
from granfe.probe import probe

SHORT = os.environ.get("GRANFE_SHORT") == "1"

# ---- parameters (SI, per unit thickness) ----------------------------------------------------
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--width", type=float, default=0.4, help="block width L [m]")
parser.add_argument("--height", type=float, default=0.2, help="block height H [m]")
parser.add_argument("--radius", type=float, default=0.002 if not SHORT else 0.004,
                    help="grain radius r [m]")
parser.add_argument("--kn", type=float, default=1.0e8, help="normal bond stiffness [N/m]")
parser.add_argument("--kt", type=float, default=3.0e7, help="tangential bond stiffness [N/m]")
parser.add_argument("--kr-factor", type=float, default=0.1, help="k_r = factor * k_t * d^2")
parser.add_argument("--punch", type=float, default=0.04, help="punch width [m]")
parser.add_argument("--settlement", type=float, default=1.0e-4, help="punch settlement [m]")
parser.add_argument("--h", type=float, default=0.02 if SHORT else 0.01, help="FE element size [m]")
parser.add_argument("--windows", type=float, nargs="+",
                    default=[0.06, 0.1] if SHORT else [0.06, 0.08, 0.1, 0.14],
                    help="half-widths of the DE window [m] (depth = half-width)")
parser.add_argument("--handshake", type=float, default=1.0,
                    help="overlap depth (FE nodes prescribed deeper than this in the window), in elements")
parser.add_argument("--ghost-width", type=float, default=2.5, help="ghost band width, in grain diameters")
parser.add_argument("--out", type=Path, default=Path("output/coupled_punch"))
args = parser.parse_args()
comm = MPI.COMM_WORLD

r, L, H = args.radius, args.width, args.height
d = 2 * r
block = lattice_block(L, H, r, args.kn, args.kt, args.kr_factor, args.punch)
x_all, top_y, centre = block.x, block.top, block.centre
constants = {k: getattr(block.material, k) for k in ("lam", "mu", "kappa", "gamma")}

# ---- 1. full DEM: every grain ---------------------------------------------------------------
t0 = time.perf_counter()
dem_all = BondedAssembly(x_all, r, find_bonds(x_all, r), args.kn, args.kt, block.kr)
full = BondedSubproblem(dem_all, np.zeros(0, int), np.concatenate([block.punch, block.base]))
full.fixed_u[: len(block.punch), 1] = -args.settlement
u_dem, theta_dem = full.solve(np.zeros((0, 2)), np.zeros(0))
t_dem = time.perf_counter() - t0
if comm.rank == 0:
    print(f"full DEM: {len(x_all)} grains, {len(dem_all.bonds)} bonds, {t_dem:.2f} s")

# ---- 2. FE only: the continuum block with the rough punch on its top --------------------------
t0 = time.perf_counter()
fe_only = fe_block(comm, block, args.h, prefix="fe_only_")
under = lambda p: np.isclose(p[1], block.surface) & (np.abs(p[0] - centre) < args.punch / 2)  # noqa: E731
fe_only.fix(under, "u", (0.0, -args.settlement))
fe_only.fix(under, "phi", 0.0)
fe_only.solve()
t_fe = time.perf_counter() - t0


def fe_at(problem, pts):
    u = fem.Function(fem.functionspace(problem.domain, ("Lagrange", 2, (2,))))
    u.interpolate(problem.w.sub(0))
    return probe(u, pts)


# ---- 3. coupled runs for several window sizes -------------------------------------------------
# errors are measured on the grains near the punch common to every window (within half the
# smallest window) and on all free grains of each window
a_min = min(args.windows)
near = np.flatnonzero((np.abs(x_all[:, 0] - centre) < a_min / 2) & (x_all[:, 1] > top_y - a_min / 2))
runs = []
for a in args.windows:
    t0 = time.perf_counter()
    problem = fe_block(comm, block, args.h, prefix=f"coupled{int(a * 1e4)}_")
    run = coupled_window(block, problem, a, a, args.ghost_width * d, args.handshake * args.h,
                         StaggeredOptions(tol=1e-8, max_iterations=300))
    its = run.press(args.settlement)
    coupling, keep = run.coupling, run.keep
    x = x_all[keep]
    t_c = time.perf_counter() - t0
    free = np.flatnonzero(coupling.kinds == 0)
    ref = u_dem[keep[free]]
    err = np.linalg.norm(coupling.u[free] - ref) / np.linalg.norm(ref)
    err_fe = np.linalg.norm(fe_at(fe_only, x[free]) - ref) / np.linalg.norm(ref)
    common = np.searchsorted(keep, near)
    ref_near = u_dem[near]
    err_near = np.linalg.norm(coupling.u[common] - ref_near) / np.linalg.norm(ref_near)
    err_fe_near = np.linalg.norm(fe_at(fe_only, x_all[near]) - ref_near) / np.linalg.norm(ref_near)
    runs.append({"window_half_width": a, "grains": int(len(x)), "free_grains": int(len(free)),
                 "iterations": its, "time_s": t_c, "timings": coupling.timings,
                 "punch_force": run.punch_force(),
                 "error_vs_full_dem": float(err_near), "fe_only_error_same_grains": float(err_fe_near),
                 "error_vs_full_dem_all_window_grains": float(err),
                 "fe_only_error_all_window_grains": float(err_fe),
                 "history": coupling.history})
    if comm.rank == 0:
        print(f"window a = {a:.3f} m: {len(x)} grains, {its} iterations, {t_c:.2f} s, "
              f"error vs full DEM near the punch {err_near:.3%} (FE only {err_fe_near:.3%}), "
              f"over the window {err:.3%} (FE only {err_fe:.3%})")
    last = (coupling, x, keep, free)

# ---- results and figures ------------------------------------------------------------------------
results = {
    "inputs": vars(args) | {"out": str(args.out), "kr": block.kr, "short": SHORT, "ranks": comm.size},
    "micropolar_constants": constants,
    "full_dem": {"grains": int(len(x_all)), "bonds": int(len(dem_all.bonds)), "time_s": t_dem,
                 "punch_grain_settlement": args.settlement,
                 "punch_force": float(-(dem_all.K @ full.q).reshape(len(x_all), 3)[block.punch, 1].sum())},
    "fe_only": {"dofs": int(fe_only.V.dofmap.index_map.size_global), "time_s": t_fe},
    "coupled": runs,
}
if comm.rank == 0:
    import matplotlib.pyplot as plt

    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=2, default=float))
    coupling, x, keep, free = last
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.5), gridspec_kw={"width_ratios": [1.6, 1.6, 1]})
    vmax = args.settlement
    axes[0].scatter(x_all[:, 0], x_all[:, 1], c=u_dem[:, 1], s=2, cmap="viridis", vmin=-vmax, vmax=0)
    axes[0].set_title(f"full DEM ({len(x_all)} grains): u_y")
    axes[1].scatter(x[:, 0], x[:, 1], c=coupling.u[:, 1], s=2, cmap="viridis", vmin=-vmax, vmax=0)
    ghost = coupling.kinds == 1
    axes[1].scatter(x[ghost, 0], x[ghost, 1], s=1, c="r", label="ghosts")
    axes[1].set_title(f"coupled: window grains ({len(x)}), u_y")
    axes[1].legend(loc="lower right")
    for ax in axes[:2]:
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
    axes[0].set_ylabel("y [m]")
    axes[1].set_xlim(axes[0].get_xlim())
    axes[1].set_ylim(axes[0].get_ylim())
    axes[2].loglog([q["time_s"] for q in runs], [q["error_vs_full_dem"] for q in runs], "o-",
                   label="coupled (window half-width)")
    for q in runs:
        axes[2].annotate(f"{q['window_half_width']:.2f} m", (q["time_s"], q["error_vs_full_dem"]))
    axes[2].axhline(runs[-1]["fe_only_error_same_grains"], color="k", ls="--", label="FE only")
    axes[2].axvline(t_dem, color="r", ls=":", label="full DEM time")
    axes[2].set_xlabel("run time [s]")
    axes[2].set_ylabel("relative error of grain displacements near the punch")
    axes[2].legend()
    fig.tight_layout()
    fig.savefig(args.out / "coupled_vs_full_dem.png", dpi=120)
    print(f"outputs in {args.out}")

# ---- checks ---------------------------------------------------------------------------------------
for q in runs:
    assert q["error_vs_full_dem"] < q["fe_only_error_same_grains"], "coupling should beat FE only"
