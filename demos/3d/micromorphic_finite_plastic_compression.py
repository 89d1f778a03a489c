"""Finite-strain micromorphic Drucker-Prager: a cube compressed 12 % between smooth and rough
platens.

This demo shows how to:

- set up finite-strain micromorphic elastoplasticity after Regueiro (2010) with
  :class:`granfe.models.micromorphic_finite_plastic.MicromorphicFiniteDruckerPrager`
  (``F = F^e F^p``, ``chi = chi^e chi^p`` and a plastic micro-gradient; a Drucker-Prager
  cone on the macro, the micro and each higher-order slice of the intermediate
  configuration; backward Euler with the exponential map), its return and consistent
  tangent computed at the quadrature points before every residual,
- compress a cube between smooth platens (symmetry planes, sides free, phi free: a
  homogeneous state) and check the axial nominal stress and the equivalent plastic strain
  against the material point by itself (:func:`~granfe.models.micromorphic_finite_return.finite_return`
  driven in uniaxial stress by scipy's root),
- compress it between rough platens that also hold the micro-structure (``u_x = u_y = 0``,
  ``phi = 0`` top and bottom): a non-homogeneous state where the higher-order level
  yields too, and the end restraint raises the mean axial stress,
- record Newton iterations and the cost of the points (each yielding point ~5-10 ms with
  its tangent).

Coupled moduli (D and five taus nonzero), hardening, non-associated flow. Trilinear u and
phi, 8 points a cell. Run: ``python demos/3d/micromorphic_finite_plastic_compression.py
[--cells 2 --steps 6 --out DIR]`` (``GRANFE_SHORT=1``: 2 steps to 4 %).
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
import scipy.optimize
from dolfinx import mesh

from granfe.models.micromorphic import MicromorphicMaterial
from granfe.models.micromorphic_drucker_prager import Cone, MicromorphicDruckerPragerMaterial
from granfe.models.micromorphic_finite_plastic import MicromorphicFiniteDruckerPrager
from granfe.models.micromorphic_finite_return import finite_return, initial_state, kernel_tables
from granfe.problem import ContinuumProblem

SHORT = os.environ.get("GRANFE_SHORT") == "1"

# ---- parameters (SI) ------------------------------------------------------------------
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--shear-modulus", type=float, default=20e6, help="mu [Pa]")
parser.add_argument("--cohesion", type=float, default=20e3, help="c of every level [Pa]")
parser.add_argument("--friction", type=float, default=30.0, help="phi [deg]")
parser.add_argument("--dilatancy", type=float, default=10.0, help="psi [deg]")
parser.add_argument("--hardening", type=float, default=2e6, help="H [Pa]")
parser.add_argument("--length", type=float, default=0.01, help="micromorphic length l [m]")
parser.add_argument("--width", type=float, default=0.1, help="cube edge [m]")
parser.add_argument("--strain", type=float, default=0.12, help="final axial compression")
parser.add_argument("--steps", type=int, default=6, help="load steps")
parser.add_argument("--cells", type=int, default=2, help="cells per edge")
parser.add_argument("--out", type=Path, default=Path("output/micromorphic_finite_plastic_compression"))
args = parser.parse_args()
comm = MPI.COMM_WORLD

mu, c, l, W = args.shear_modulus, args.cohesion, args.length, args.width
L2 = mu * l**2
strains = (np.linspace(0, 0.04, 3)[1:] if SHORT
           else np.linspace(0, args.strain, args.steps + 1)[1:])
ELASTIC = MicromorphicMaterial(lam=mu, mu=mu, eta=0.25 * mu, tau=0.1 * mu, kappa=0.75 * mu,
                               nu=0.15 * mu, sigma=0.075 * mu, tau1=0.1 * L2, tau2=0.05 * L2,
                               tau3=0.0, tau4=0.1 * L2, tau5=0.0, tau6=0.0, tau7=L2,
                               tau8=0.05 * L2, tau9=0.0, tau10=0.0, tau11=0.02 * L2)
cone = (args.friction, args.dilatancy)
MATERIAL = MicromorphicDruckerPragerMaterial(
    ELASTIC, macro=Cone(c, *cone, args.hardening), micro=Cone(c, *cone, args.hardening),
    gradient=Cone(c * l, *cone, args.hardening * l**2))


def at(axis, value):
    return lambda x: np.isclose(x[axis], value)


# ---- the material point by itself --------------------------------------------------------
def point_uniaxial():
    """Axial nominal stress P_zz and macro equivalent plastic strain of one point in
    uniaxial stress (P_xx = P_yy = 0, Q = 0 by scipy's root on u_x,x, u_y,y and phi)."""
    tab = kernel_tables(MATERIAL)
    state, v, rows, out = initial_state(), np.zeros(11), np.r_[0, 4, 9:18], []

    def fields(v, ezz):
        return np.diag([v[0], v[1], ezz]), np.eye(3) + v[2:].reshape(3, 3), np.zeros((3, 3, 3))

    for e in strains:
        def residual(v, ezz=-e, state=state):
            info = finite_return(*fields(v, ezz), state, MATERIAL, tab, tangent=True)[4]
            return info["nominal"][rows] / mu, info["tangent"][np.ix_(rows, rows)] / mu

        v = scipy.optimize.root(residual, v, jac=True, method="hybr",
                                options={"xtol": 1e-14}).x
        _, _, _, state, info = finite_return(*fields(v, -e), state, MATERIAL, tab)
        out.append({"axial_stress": float(info["nominal"][8]), "eq_macro": float(state["eq"][0])})
    return out


# ---- the cube ------------------------------------------------------------------------------
def compression(rough: bool):
    """The cube pushed down step by step; per step the mean axial nominal stress (reaction
    over the reference area), Newton iterations, the largest equivalent plastic strain of
    each level and the wall time."""
    domain = mesh.create_box(comm, [[0.0, 0.0, 0.0], [W, W, W]], [args.cells] * 3,
                             mesh.CellType.hexahedron)
    p = ContinuumProblem(domain, MicromorphicFiniteDruckerPrager(MATERIAL), degree=(1, 1),
                         quadrature_degree=2, prefix=f"mmfdp_{'rough' if rough else 'smooth'}_")
    bottom, top = at(2, 0.0), at(2, W)
    if rough:
        p.fix(bottom, "u")
        p.fix(bottom, "phi")
        p.fix(top, "u_x")
        p.fix(top, "u_y")
        p.fix(top, "phi")
    else:
        for axis, name in enumerate(("u_x", "u_y", "u_z")):
            p.fix(at(axis, 0.0), name)
    drive = p.fix(top, "u_z", 0.0)
    rows = []
    for e in strains:
        drive.value = -e * W
        t0 = time.perf_counter()
        its = p.solve()
        eq = p.state.owned("equivalent_plastic_strain").reshape(-1, 5)
        eq = np.array([comm.allreduce(float(eq[:, i].max(initial=0.0)), op=MPI.MAX)
                       for i in range(5)])
        rows.append({"axial_strain": float(e), "newton_iterations": its,
                     "axial_stress": float(p.reaction(top, "u_z") / W**2),
                     "eq_max": {"macro": eq[0], "micro": eq[1], "gradient": float(eq[2:].max())},
                     "seconds": time.perf_counter() - t0})
    return rows


t_start = time.perf_counter()
point = point_uniaxial()
smooth = compression(rough=False)
rough = compression(rough=True)
smooth_error = max(abs(s["axial_stress"] / q["axial_stress"] - 1) for s, q in zip(smooth, point, strict=True))
results = {
    "inputs": {"mu": mu, "cohesion": c, "friction_deg": args.friction,
               "dilatancy_deg": args.dilatancy, "hardening": args.hardening, "length": l,
               "width": W, "strains": strains.tolist(), "cells": args.cells,
               "degree": [1, 1], "quadrature_degree": 2, "short": SHORT, "ranks": comm.size},
    "point": point, "smooth": smooth, "rough": rough,
    "figures": {"smooth_vs_point_max_rel_error": smooth_error,
                "rough_over_smooth_final_stress": rough[-1]["axial_stress"] / smooth[-1]["axial_stress"],
                "max_newton_iterations": max(r["newton_iterations"] for r in smooth + rough),
                "seconds": time.perf_counter() - t_start},
}

if comm.rank == 0:
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    for name, rows in (("smooth", smooth), ("rough", rough)):
        for r in rows:
            print(f"{name} {r['axial_strain']:5.3f}: P_zz {r['axial_stress'] / 1e3:9.2f} kPa, "
                  f"{r['newton_iterations']} its, eq max macro {r['eq_max']['macro']:.4f} micro "
                  f"{r['eq_max']['micro']:.4f} gradient {r['eq_max']['gradient']:.3f}, "
                  f"{r['seconds']:.1f} s")
    f = results["figures"]
    print(f"smooth platens against the point: {f['smooth_vs_point_max_rel_error']:.1e}; rough / "
          f"smooth final stress {f['rough_over_smooth_final_stress']:.4f}; "
          f"{f['seconds']:.1f} s; outputs in {args.out}")

# ---- checks -------------------------------------------------------------------------------
assert smooth_error < 1e-8, smooth_error                  # a homogeneous state: the point
assert all(r["eq_max"]["micro"] == 0 for r in smooth)      # Q = 0: no micro stress
assert rough[-1]["axial_stress"] < smooth[-1]["axial_stress"] < 0    # restraint: stronger
assert rough[-1]["eq_max"]["gradient"] > 0                 # the higher-order level yields
assert results["figures"]["max_newton_iterations"] <= 10
