"""Mandel's problem: a saturated poroelastic specimen squeezed between rigid plates (Biot u-p).

This demo shows how to:

- solve Mandel's plane-strain problem on a quarter of the specimen: symmetry on two sides,
  a free drained side, a rigid frictionless impermeable plate carrying a prescribed force
  (:meth:`granfe.consolidation.Consolidation.step_with_resultant`, the plate's settlement
  found from two trial solves of the affine step),
- apply the force undrained at t = 0+ (uniform pore pressure ``B (1 + nu_u) F / 3a``),
- see the Mandel-Cryer effect: the pore pressure at the centre *rises* above its undrained
  value before it decays, because the drained edges soften and hand load to the core,
- compare the pressure profiles, the centre pressure and the plate settlement with the
  closed form (Abousleiman et al. 1996; Cheng & Detournay 1988),
- write ``results.json``, ``mandel.png`` and the fields (VTX) to ``--out``.

Run: ``python demos/2d/mandel.py`` (or under ``mpiexec -n 2``); ``GRANFE_SHORT=1`` for a short
run.
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

from granfe.consolidation import Consolidation, mandel_pressure, mandel_top_displacement, time_grid
from granfe.io import ContinuumWriter
from granfe.models.poroelastic import PoreFluid, Poroelastic, PoroelasticMaterial
from granfe.probe import probe
from granfe.problem import ContinuumProblem

SHORT = os.environ.get("GRANFE_SHORT") == "1"

# ---- parameters (SI) ------------------------------------------------------------------
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--a", type=float, default=0.05, help="half-width of the specimen [m]")
parser.add_argument("--b", type=float, default=0.05, help="half-height of the specimen [m]")
parser.add_argument("--force", type=float, default=1.0e4,
                    help="plate force per unit thickness on the half-width a, F [N/m] (2F in all)")
parser.add_argument("--E", type=float, default=1.0e8, help="drained Young's modulus [Pa]")
parser.add_argument("--nu", type=float, default=0.1, help="drained Poisson's ratio")
parser.add_argument("--k", type=float, default=1.0e-15, help="intrinsic permeability [m^2]")
parser.add_argument("--mu-f", type=float, default=1.0e-3, help="water viscosity [Pa s]")
parser.add_argument("--porosity", type=float, default=0.3)
parser.add_argument("--K-f", type=float, default=2.2e9, help="water bulk modulus [Pa]")
parser.add_argument("--K-s", type=float, default=3.6e10, help="grain bulk modulus [Pa]")
parser.add_argument("--cells", type=int, default=None, help="cells per side of the quarter")
parser.add_argument("--steps", type=int, default=None, help="time steps to T = c t / a^2 = 1.5")
parser.add_argument("--out", type=Path, default=Path("output/mandel"))
args = parser.parse_args()
comm = MPI.COMM_WORLD

a, b, F = args.a, args.b, args.force
cells = args.cells or (10 if SHORT else 20)
steps = args.steps or (50 if SHORT else 250)
T_OUT = [0.01, 0.05, 0.1, 0.2, 0.5, 1.0, 1.5]             # output times, c t / a^2


def log(msg):
    if comm.rank == 0:
        print(msg, flush=True)


# ---- material -------------------------------------------------------------------------
K_drained = args.E / (3 * (1 - 2 * args.nu))
fluid = PoreFluid.from_constituents(k=args.k, mu_f=args.mu_f, porosity=args.porosity,
                                    K_f=args.K_f, K_drained=K_drained, K_s=args.K_s)
rock = PoroelasticMaterial.from_engineering(args.E, args.nu, fluid)
c = rock.c_mandel
t_c = a**2 / c
p0 = F * rock.B * (1 + rock.nu_u) / (3 * a)                # undrained pore pressure [Pa]
log(f"alpha = {fluid.alpha:.4f}, M = {fluid.M:.3e} Pa, B = {rock.B:.4f}, nu_u = {rock.nu_u:.4f}, "
    f"c = {c:.3e} m^2/s, a^2/c = {t_c:.1f} s, p0 = {p0:.1f} Pa")

# ---- set-up: the quarter 0 < x < a, 0 < y < b ------------------------------------------
domain = mesh.create_rectangle(comm, [[0.0, 0.0], [a, b]], [cells, cells])
xi = domain.geometry.x[:, 0] / a
domain.geometry.x[:, 0] = a * (xi + 0.5 * xi * (1 - xi))   # half-size cells at the drained side
problem = ContinuumProblem(domain, Poroelastic(rock), prefix="mandel_")


def plate_face(x):
    return np.isclose(x[1], b)


problem.fix(lambda x: np.isclose(x[0], 0.0), "u_x")        # symmetry (impermeable: natural)
problem.fix(lambda x: np.isclose(x[1], 0.0), "u_y")        # symmetry
problem.fix(lambda x: np.isclose(x[0], a), "p", 0.0)       # free side, drained
plate = problem.fix(plate_face, "u_y", 0.0)                # rigid frictionless plate
run = Consolidation(problem)

xs = np.linspace(0.0, a, 101)
points = np.c_[xs, np.full_like(xs, b / 2), np.zeros_like(xs)]


def pressure():
    return probe(problem.w.sub(1).collapse(), points)[:, 0]


# ---- solve ----------------------------------------------------------------------------
t0 = time.perf_counter()
run.step_with_resultant(0.0, plate, plate_face, "u_y", -F)       # undrained, t = 0+
p = pressure()
undrained = {"p_rel": float(np.abs(p / p0 - 1).max()),
             "plate": float(plate.value),
             "plate_exact": -F * (1 - rock.nu_u) * b / (2 * rock.G * a)}
undrained["plate_rel"] = abs(undrained["plate"] / undrained["plate_exact"] - 1)
log(f"t = 0+: |p / p0 - 1| <= {undrained['p_rel']:.1e}, plate settlement error "
    f"{undrained['plate_rel']:.1e}")
history = [(0.0, float(p[0]), float(plate.value))]
profiles = []
for T in time_grid(T_OUT[-1], steps, 3.0, T_OUT):
    run.step_with_resultant(T * t_c - run.t, plate, plate_face, "u_y", -F)
    p = pressure()
    history.append((run.t, float(p[0]), float(plate.value)))
    if np.any(np.isclose(T, T_OUT)):
        exact = mandel_pressure(xs, run.t, a=a, F=F, material=rock)
        d = mandel_top_displacement(run.t, a=a, b=b, F=F, material=rock)
        profiles.append({"T": T, "t": run.t, "p": p.tolist(), "p_exact": exact.tolist(),
                         "p_error": float(np.abs(p - exact).max() / p0),
                         "plate": float(plate.value), "plate_exact": d,
                         "plate_error": abs(float(plate.value) / d - 1)})
        log(f"T = {T:5.3f}: max |p - p_exact| / p0 = {100 * profiles[-1]['p_error']:.3f} %, "
            f"plate {1e6 * plate.value:.3f} um ({100 * profiles[-1]['plate_error']:.3f} %)")
wall = time.perf_counter() - t0
with ContinuumWriter(problem, args.out, name="mandel") as writer:
    writer.write(run.t)

# ---- the centre pressure: Mandel-Cryer -------------------------------------------------
t_h, p_centre, plate_h = np.array(history[1:]).T
p_centre_exact = np.array([mandel_pressure(0.0, t, a=a, F=F, material=rock) for t in t_h])
late = t_h >= 0.01 * t_c                          # resolved by the mesh (boundary layer > 2 cells)
i_fe, i_ex = int(p_centre.argmax()), int(p_centre_exact.argmax())
cryer = {"peak_fe": float(p_centre[i_fe] / p0), "T_peak_fe": float(t_h[i_fe] / t_c),
         "peak_exact": float(p_centre_exact[i_ex] / p0), "T_peak_exact": float(t_h[i_ex] / t_c),
         "centre_error_max_T_ge_0.01": float(np.abs(p_centre - p_centre_exact)[late].max() / p0)}
log(f"Mandel-Cryer: centre peak {cryer['peak_fe']:.4f} p0 at T = {cryer['T_peak_fe']:.3f} "
    f"(closed form {cryer['peak_exact']:.4f} p0 at T = {cryer['T_peak_exact']:.3f}); worst centre "
    f"error for T >= 0.01: {100 * cryer['centre_error_max_T_ge_0.01']:.3f} % of p0")

results = {
    "inputs": {"a": a, "b": b, "F": F, "E": args.E, "nu": args.nu, "k": args.k, "mu_f": args.mu_f,
               "porosity": args.porosity, "K_f": args.K_f, "K_s": args.K_s, "cells": cells,
               "mesh_grading": "x -> x + x (1 - x) / 2 (cells half as wide at the drained side)",
               "steps": steps, "time_grid_power": 3.0, "degree": [2, 1], "ranks": comm.size,
               "short": SHORT},
    "references": {"alpha": fluid.alpha, "M": fluid.M, "B": rock.B, "nu_u": rock.nu_u, "c": c,
                   "t_c": t_c, "p0": p0,
                   "source": "Abousleiman et al. 1996 (Cheng & Detournay 1988), "
                             "400 terms"},
    "errors": {"p_max_over_p0": max(r["p_error"] for r in profiles),
               "plate_max_rel": max(r["plate_error"] for r in profiles),
               "undrained": undrained,
               "per_time": [{k: r[k] for k in ("T", "p_error", "plate_error")} for r in profiles]},
    "mandel_cryer": cryer,
    "wall_s": wall,
    "dofs": problem.V.dofmap.index_map.size_global * problem.V.dofmap.index_map_bs,
    "profiles": profiles,
    "history": {"t": t_h.tolist(), "p_centre": p_centre.tolist(),
                "p_centre_exact": p_centre_exact.tolist(), "plate": plate_h.tolist()},
}
log(f"{len(t_h)} steps in {wall:.1f} s; worst pressure error "
    f"{100 * results['errors']['p_max_over_p0']:.3f} % of p0, worst plate settlement error "
    f"{100 * results['errors']['plate_max_rel']:.3f} %")

# ---- plots ----------------------------------------------------------------------------
if comm.rank == 0:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2, ax3) = plt.subplots(1, 3, figsize=(14, 4.2))
    for r in profiles:
        line, = ax1.plot(xs / a, np.array(r["p_exact"]) / p0, lw=1)
        ax1.plot(xs[::5] / a, np.array(r["p"])[::5] / p0, "o", ms=3, color=line.get_color(),
                 label=f"T = {r['T']:g}")
    ax1.set_xlabel("x / a")
    ax1.set_ylabel("p / p0")
    ax1.set_title("pore pressure at y = b/2: FE (dots), closed form")
    ax1.legend(fontsize=7)
    ax1.grid(alpha=0.3)
    tt = np.geomspace(1e-4 * t_c, t_h[-1], 300)
    pick = np.unique(np.searchsorted(t_h, np.geomspace(1e-4 * t_c, t_h[-1], 60)).clip(0, len(t_h) - 1))
    ax2.semilogx(tt / t_c, [mandel_pressure(0.0, t, a=a, F=F, material=rock) / p0 for t in tt],
                 "k-", lw=1, label="closed form")
    ax2.semilogx(t_h[pick] / t_c, p_centre[pick] / p0, "o", mfc="none", ms=4, label="FE")
    ax2.axhline(1.0, ls=":", color="gray", lw=0.8)
    ax2.set_xlabel("T = c t / a^2")
    ax2.set_ylabel("p(0, t) / p0")
    ax2.set_title(f"centre pressure (Mandel-Cryer peak {cryer['peak_fe']:.3f})")
    ax2.legend(fontsize=8)
    ax2.grid(alpha=0.3)
    ax3.semilogx(tt / t_c, [1e6 * mandel_top_displacement(t, a=a, b=b, F=F, material=rock) for t in tt],
                 "k-", lw=1, label="closed form")
    ax3.semilogx(t_h[pick] / t_c, 1e6 * plate_h[pick], "o", mfc="none", ms=4, label="FE")
    ax3.set_xlabel("T = c t / a^2")
    ax3.set_ylabel("plate displacement u_y(b) [um]")
    ax3.set_title(f"plate ({cells} x {cells} cells, {len(t_h)} steps)")
    ax3.legend(fontsize=8)
    ax3.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(args.out / "mandel.png", dpi=120)
    (args.out / "results.json").write_text(json.dumps(results, indent=1))

# ---- checks ---------------------------------------------------------------------------
tolerance = 0.03 if SHORT else 0.01
assert results["errors"]["p_max_over_p0"] < tolerance, results["errors"]
assert results["errors"]["plate_max_rel"] < tolerance, results["errors"]
assert cryer["centre_error_max_T_ge_0.01"] < tolerance, cryer
assert cryer["peak_fe"] > 1.05 and abs(cryer["peak_fe"] - cryer["peak_exact"]) < tolerance, cryer
assert undrained["p_rel"] < 1e-8 and undrained["plate_rel"] < 1e-8, undrained
