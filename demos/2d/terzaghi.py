"""Terzaghi's one-dimensional consolidation of a saturated clay layer (Biot u-p).

This demo shows how to:

- describe a saturated soil by its drained skeleton and a pore fluid (Biot coefficient and
  modulus from the porosity and the water's bulk modulus),
- set up a Biot problem (:class:`granfe.models.poroelastic.Poroelastic`, Taylor-Hood P2/P1)
  in uniaxial strain: a column with a drained, loaded top and an impermeable base,
- apply the load undrained at t = 0+ and let the layer consolidate with backward-Euler
  steps (:class:`granfe.consolidation.Consolidation`),
- compare the pore-pressure profiles and the settlement with Terzaghi's series solution,
- write ``results.json``, ``terzaghi.png`` and the fields (VTX) to ``--out``.

Run: ``python demos/2d/terzaghi.py`` (or under ``mpiexec -n 2``); ``GRANFE_SHORT=1`` for a
short run.
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
from dolfinx import mesh

from granfe.consolidation import (
    Consolidation,
    terzaghi_p0,
    terzaghi_pressure,
    terzaghi_settlement,
    time_grid,
)
from granfe.io import ContinuumWriter
from granfe.models.poroelastic import PoreFluid, Poroelastic, PoroelasticMaterial
from granfe.probe import probe
from granfe.problem import ContinuumProblem

SHORT = os.environ.get("GRANFE_SHORT") == "1"

# ---- parameters (SI) ------------------------------------------------------------------
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--height", type=float, default=5.0, help="layer thickness H [m]")
parser.add_argument("--load", type=float, default=1.0e5, help="surface load q [Pa]")
parser.add_argument("--E", type=float, default=1.0e7, help="drained Young's modulus [Pa]")
parser.add_argument("--nu", type=float, default=0.25, help="drained Poisson's ratio")
parser.add_argument("--k", type=float, default=1.0e-14, help="intrinsic permeability [m^2]")
parser.add_argument("--mu-f", type=float, default=1.0e-3, help="water viscosity [Pa s]")
parser.add_argument("--porosity", type=float, default=0.4)
parser.add_argument("--K-f", type=float, default=2.2e9, help="water bulk modulus [Pa]")
parser.add_argument("--K-s", type=float, default=3.6e10, help="grain bulk modulus [Pa]")
parser.add_argument("--cells", type=int, default=None, help="cells over the height")
parser.add_argument("--steps", type=int, default=None, help="time steps to T = c t / H^2 = 2")
parser.add_argument("--out", type=Path, default=Path("output/terzaghi"))
args = parser.parse_args()
comm = MPI.COMM_WORLD

H, q = args.height, args.load
width = H / 20
cells = args.cells or (20 if SHORT else 40)
steps = args.steps or (60 if SHORT else 300)
T_OUT = [0.005, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0]     # output times, c t / H^2


def log(msg):
    if comm.rank == 0:
        print(msg, flush=True)


# ---- material -------------------------------------------------------------------------
K_drained = args.E / (3 * (1 - 2 * args.nu))
fluid = PoreFluid.from_constituents(k=args.k, mu_f=args.mu_f, porosity=args.porosity,
                                    K_f=args.K_f, K_drained=K_drained, K_s=args.K_s)
soil = PoroelasticMaterial.from_engineering(args.E, args.nu, fluid)
c = soil.c_oedometric
t_c = H**2 / c                                  # consolidation time scale [s]
p0 = terzaghi_p0(q, soil)                       # undrained pore pressure [Pa]
log(f"alpha = {fluid.alpha:.4f}, M = {fluid.M:.3e} Pa, B = {soil.B:.4f}, c_v = {c:.3e} m^2/s, "
    f"H^2/c_v = {t_c / 86400:.2f} days, p0 = {p0 / q:.4f} q")

# ---- set-up: a column in uniaxial strain ------------------------------------------------
domain = mesh.create_rectangle(comm, [[0.0, 0.0], [width, H]], [1, cells],
                               cell_type=mesh.CellType.quadrilateral)
problem = ContinuumProblem(domain, Poroelastic(soil), prefix="terzaghi_")


def top(x):
    return np.isclose(x[1], H)


problem.fix(lambda x: np.isclose(x[1], 0.0), "u_y")                      # rigid base
problem.fix(lambda x: np.isclose(x[0], 0.0) | np.isclose(x[0], width), "u_x")  # oedometer walls
problem.fix(top, "p", 0.0)                                               # drained top
problem.traction(top, (0.0, -q))                                         # the load
run = Consolidation(problem)

ys = np.linspace(0.0, H, 101)
points = np.c_[np.full_like(ys, width / 2), ys, np.zeros_like(ys)]


def pressure():
    return probe(problem.w.sub(1).collapse(), points)[:, 0]


def settlement():
    return -float(probe(problem.w.sub(0).collapse(), np.array([[width / 2, H, 0.0]]))[0, 1])


# ---- solve ----------------------------------------------------------------------------
t0 = time.perf_counter()
run.undrained()
s_undrained = settlement()
p_undrained_error = float(np.abs(pressure() / p0 - 1).max())   # uniform p0, the top too
profiles, curve = [], [(0.0, s_undrained)]
for T in time_grid(T_OUT[-1], steps, 3.0, T_OUT):
    run.step(T * t_c - run.t)
    curve.append((run.t, settlement()))
    if np.any(np.isclose(T, T_OUT)):
        p = pressure()
        exact = terzaghi_pressure(H - ys, run.t, H=H, p0=p0, c=c)
        s_exact = terzaghi_settlement(run.t, H=H, q=q, material=soil)
        profiles.append({"T": T, "t": run.t, "p": p.tolist(), "p_exact": exact.tolist(),
                         "p_error": float(np.abs(p - exact).max() / p0),
                         "settlement": curve[-1][1], "settlement_exact": s_exact,
                         "settlement_error": abs(curve[-1][1] / s_exact - 1)})
        log(f"T = {T:5.3f}: max |p - p_exact| / p0 = {100 * profiles[-1]['p_error']:.3f} %, "
            f"settlement {1e3 * curve[-1][1]:.3f} mm ({100 * profiles[-1]['settlement_error']:.3f} %)")
wall = time.perf_counter() - t0
with ContinuumWriter(problem, args.out, name="terzaghi") as writer:
    writer.write(run.t)

# ---- results and plots ----------------------------------------------------------------
s_undrained_exact = q * H / (soil.oedometric_modulus + fluid.alpha**2 * fluid.M)
s_drained = q * H / soil.oedometric_modulus
results = {
    "inputs": {"H": H, "width": width, "q": q, "E": args.E, "nu": args.nu, "k": args.k,
               "mu_f": args.mu_f, "porosity": args.porosity, "K_f": args.K_f, "K_s": args.K_s,
               "cells": cells, "steps": steps, "time_grid_power": 3.0, "degree": [2, 1],
               "cell_type": "quadrilateral", "ranks": comm.size, "short": SHORT},
    "references": {"alpha": fluid.alpha, "M": fluid.M, "B": soil.B, "c_v": c, "t_c": t_c,
                   "p0": p0, "settlement_undrained": s_undrained_exact,
                   "settlement_drained": s_drained,
                   "source": "Terzaghi 1925 series (Wang 2000, ch. 6), 400 terms"},
    "errors": {"p_max_over_p0": max(r["p_error"] for r in profiles),
               "settlement_max_rel": max(r["settlement_error"] for r in profiles),
               "undrained_p_rel": p_undrained_error,
               "undrained_settlement_rel": abs(s_undrained / s_undrained_exact - 1),
               "per_time": [{k: r[k] for k in ("T", "p_error", "settlement_error")}
                            for r in profiles]},
    "wall_s": wall,
    "dofs": problem.V.dofmap.index_map.size_global * problem.V.dofmap.index_map_bs,
    "profiles": profiles,
    "curve": curve,
}
log(f"{len(curve) - 1} steps in {wall:.1f} s; worst pressure error "
    f"{100 * results['errors']['p_max_over_p0']:.3f} % of p0, worst settlement error "
    f"{100 * results['errors']['settlement_max_rel']:.3f} %")

if comm.rank == 0:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4.2))
    for r in profiles:
        line, = ax1.plot(np.array(r["p_exact"]) / p0, ys / H, lw=1)
        ax1.plot(np.array(r["p"])[::5] / p0, ys[::5] / H, "o", ms=3, color=line.get_color(),
                 label=f"T = {r['T']:g}")
    ax1.set_xlabel("p / p0")
    ax1.set_ylabel("height above the impermeable base / H")
    ax1.set_title("pore pressure: FE (dots), Terzaghi (lines)")
    ax1.legend(fontsize=7)
    ax1.grid(alpha=0.3)
    t, s = np.array(curve[1:]).T
    tt = np.geomspace(t[0], t[-1], 200)
    ax2.semilogx(tt / t_c, [1e3 * terzaghi_settlement(x, H=H, q=q, material=soil) for x in tt],
                 "k-", lw=1, label="Terzaghi")
    pick = np.unique(np.searchsorted(t, np.geomspace(t[0], t[-1], 50)).clip(0, len(t) - 1))
    ax2.semilogx(t[pick] / t_c, 1e3 * s[pick], "o", mfc="none", ms=4, label="FE (backward Euler)")
    ax2.axhline(1e3 * s_drained, ls="--", color="gray", lw=0.8, label="drained")
    ax2.axhline(1e3 * s_undrained_exact, ls=":", color="gray", lw=0.8, label="undrained")
    ax2.set_xlabel("T = c_v t / H^2")
    ax2.set_ylabel("settlement [mm]")
    ax2.set_title(f"settlement ({cells} cells, {len(t)} steps)")
    ax2.legend(fontsize=8)
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(args.out / "terzaghi.png", dpi=120)
    (args.out / "results.json").write_text(json.dumps(results, indent=1))

# ---- checks ---------------------------------------------------------------------------
tolerance = 0.03 if SHORT else 0.01
assert results["errors"]["p_max_over_p0"] < tolerance, results["errors"]
assert results["errors"]["settlement_max_rel"] < tolerance, results["errors"]
assert results["errors"]["undrained_settlement_rel"] < 1e-8, results["errors"]
assert p_undrained_error < 1e-8, p_undrained_error
