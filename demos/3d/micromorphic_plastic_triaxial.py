"""Triaxial compression of a micromorphic Drucker-Prager solid (three plastic levels).

This demo shows how to:

- set up small-strain micromorphic plasticity after Regueiro (2009, 2010) with
  :class:`granfe.models.micromorphic_drucker_prager.MicromorphicDruckerPrager`: one
  Drucker-Prager cone (Mohr-Coulomb compression-meridian match, non-associated flow,
  linear hardening) on the macro stress, on the symmetric relative stress and on each slice
  of the higher-order stress, returned in closed form at the quadrature points,
- run homogeneous triaxial compression at three confining stresses with an unload-reload
  cycle (3 % -> 2.8 % -> 4 %), and check the peaks against Mohr-Coulomb and the dilatancy against the flow rule,
- load the micro level alone (u held, a body double force confining the relative stress)
  and check its peak against the micro cone's Mohr-Coulomb value,
- compress a prism between rough platens that also hold the micro-structure (phi = 0),
  for two length scales l of the higher-order moduli (tau7 = mu l^2, gradient cohesion
  c l): the end restraint and the higher-order level raise the mean axial stress above
  the homogeneous peak, more with a larger l,
- switch on coupled moduli (tau, sigma and five more taus) with
  :class:`granfe.models.micromorphic_iterative.MicromorphicDruckerPragerIterative`, whose
  levels return together by Newton at the quadrature points, and check it against the
  closed-form model on the decoupled set.

Run: ``mpiexec -n 2 python demos/3d/micromorphic_plastic_triaxial.py [--out DIR]``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from dataclasses import replace
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import ufl
from dolfinx import fem, mesh

from granfe.models.micromorphic import MicromorphicMaterial
from granfe.models.micromorphic_drucker_prager import (
    Cone,
    MicromorphicDruckerPrager,
    MicromorphicDruckerPragerMaterial,
)
from granfe.models.micromorphic_iterative import MicromorphicDruckerPragerIterative
from granfe.probe import probe
from granfe.problem import ContinuumProblem

SHORT = os.environ.get("GRANFE_SHORT") == "1"

# ---- parameters (SI) ------------------------------------------------------------------
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--shear-modulus", type=float, default=20e6, help="mu [Pa]")
parser.add_argument("--lame", type=float, default=20e6, help="lam [Pa]")
parser.add_argument("--cohesion", type=float, default=10e3, help="c of every level [Pa]")
parser.add_argument("--friction", type=float, default=30.0, help="phi [deg]")
parser.add_argument("--dilatancy", type=float, default=10.0, help="psi [deg]")
parser.add_argument("--confinements", type=float, nargs="+", default=(50e3, 100e3, 200e3),
                    help="sigma_3 of the homogeneous tests [Pa]")
parser.add_argument("--width", type=float, default=0.05, help="prism width [m]")
parser.add_argument("--lengths", type=float, nargs=2, default=(0.002, 0.01),
                    help="micromorphic lengths l of the platen runs [m]")
parser.add_argument("--cells", type=int, default=4, help="cells across the prism width")
parser.add_argument("--out", type=Path, default=Path("output/micromorphic_plastic_triaxial"))
args = parser.parse_args()
comm = MPI.COMM_WORLD

mu, lam, c, phi_f, psi = args.shear_modulus, args.lame, args.cohesion, args.friction, args.dilatancy
young = mu * (3 * lam + 2 * mu) / (lam + mu)
cells = 2 if SHORT else args.cells
confinements = tuple(args.confinements)[1:2] if SHORT else tuple(args.confinements)


def elastic(length):
    """Decoupled micromorphic moduli (D = 0, C = tau7 I) with tau7 = mu l^2."""
    return MicromorphicMaterial(lam=lam, mu=mu, eta=0.25 * mu, tau=0.0, kappa=0.75 * mu,
                                nu=0.15 * mu, sigma=0.0, tau7=mu * length**2,
                                **{f"tau{i}": 0.0 for i in range(1, 12) if i != 7})


def material(length, hardening=0.0):
    return MicromorphicDruckerPragerMaterial(
        elastic(length), macro=Cone(c, phi_f, psi, hardening), micro=Cone(c, phi_f, psi, hardening),
        gradient=Cone(c * length, phi_f, psi, hardening * length**2))


def mohr_coulomb_peak(sigma3):
    t = math.tan(math.radians(45 + phi_f / 2))
    return sigma3 * t**2 + 2 * c * t


def at(axis, value):
    return lambda x: np.isclose(x[axis], value)


def everywhere(x):
    return np.full(x.shape[1], True)


# ---- 1. homogeneous triaxial compression (macro level) ------------------------------------
def triaxial(sigma3):
    """Unit cube with symmetry planes, confining traction on x = 1, y = 1, the top pushed
    down to 3 %, back to 2 % and on to 4 %; phi free (no relative stress)."""
    p = ContinuumProblem(mesh.create_unit_cube(comm, 1, 1, 1),
                         MicromorphicDruckerPrager(material(args.lengths[0])),
                         prefix=f"mmdptri{int(sigma3)}_")
    for axis, name in enumerate(("u_x", "u_y", "u_z")):
        p.fix(at(axis, 0.0), name)
    p.traction(at(0, 1.0), (-sigma3, 0.0, 0.0))
    p.traction(at(1, 1.0), (0.0, -sigma3, 0.0))
    top = p.fix(at(2, 1.0), "u_z", 0.0)
    path = np.concatenate([np.linspace(0, 0.03, 13)[1:], [0.029, 0.028, 0.029, 0.03, 0.035, 0.04]])
    rows = []
    for strain in path:
        top.value = -strain
        its = p.solve()
        u = probe(p.w.sub(0).collapse(), np.array([[1.0, 1.0, 1.0]]))[0]
        rows.append({"axial_strain": float(strain), "axial_stress": -p.reaction(at(2, 1.0), "u_z"),
                     "volumetric_strain": float(-u.sum()), "newton_iterations": its})
    peak = max(r["axial_stress"] for r in rows)
    (a1, v1), (a2, v2) = [(r["axial_strain"], r["volumetric_strain"]) for r in rows[-2:]]
    _, B, _ = Cone(c, phi_f, psi).constants
    unload = (rows[11]["axial_stress"] - rows[13]["axial_stress"]) / 0.002
    return {"sigma3": sigma3, "path": rows, "peak": peak, "mohr_coulomb": mohr_coulomb_peak(sigma3),
            "rel_error_peak": abs(peak / mohr_coulomb_peak(sigma3) - 1),
            "dilatancy_ratio": (v2 - v1) / (a2 - a1),
            "dilatancy_ratio_flow_rule": B / (B / 3 - 1 / math.sqrt(3)),
            "unloading_modulus": unload, "young": young}


# ---- 2. the micro level alone -----------------------------------------------------------
def micro_triaxial(sigma3):
    """u = 0, phi homogeneous: the relative stress equals the body double force l (the micro
    balance), l = -sigma3 on xx, yy; phi_zz driven to -6 %."""
    p = ContinuumProblem(mesh.create_unit_cube(comm, 1, 1, 1),
                         MicromorphicDruckerPrager(material(args.lengths[0])), prefix="mmdpmicro_")
    p.fix_everywhere("u")
    p.body_load("phi", ufl.as_matrix([[-sigma3, 0, 0], [0, -sigma3, 0], [0, 0, 0]]))
    drive = p.fix(everywhere, "phi_zz", 0.0)
    Q = p.state.committed["yielding"].function_space
    ncells = p.domain.topology.index_map(3).size_local
    expr = fem.Expression(p.stresses()["relative_stress"][2, 2], Q.element.interpolation_points)
    rows = []
    for b in np.linspace(0, 0.06, 13)[1:]:
        drive.value = -b
        p.solve()
        local = expr.eval(p.domain, np.arange(ncells, dtype=np.int32))
        Tzz = comm.allreduce(float(local.max()) if local.size else -np.inf, MPI.MAX)
        rows.append({"phi_zz": float(-b), "relative_stress_zz": Tzz})
    peak = max(-r["relative_stress_zz"] for r in rows)
    return {"sigma3": sigma3, "path": rows, "peak": peak, "mohr_coulomb": mohr_coulomb_peak(sigma3),
            "rel_error_peak": abs(peak / mohr_coulomb_peak(sigma3) - 1)}


# ---- 3. rough platens, two length scales ---------------------------------------------------
def platens(length, sigma3=100e3, model=None, name="", quadrature_degree=None):
    """Prism width x width x 2 width: platens at z = 0 and z = 2 width hold u_x = u_y = 0 and
    phi = 0; the top moves down; confining traction on the four sides."""
    w = args.width
    domain = mesh.create_box(comm, [[0.0, 0.0, 0.0], [w, w, 2 * w]], [cells, cells, 2 * cells])
    model = model or MicromorphicDruckerPrager(material(length, hardening=0.0))
    p = ContinuumProblem(domain, model, prefix=f"mmdpplat{length:g}{name}_",
                         quadrature_degree=quadrature_degree)
    bottom, top = at(2, 0.0), at(2, 2 * w)
    p.fix(bottom, "u")
    p.fix(bottom, "phi")
    p.fix(top, "u_x")
    p.fix(top, "u_y")
    p.fix(top, "phi")
    drive = p.fix(top, "u_z", 0.0)
    for axis in (0, 1):
        for side, sign in ((0.0, -1.0), (w, 1.0)):
            load = [0.0, 0.0, 0.0]
            load[axis] = -sign * sigma3
            p.traction(at(axis, side), tuple(load))
    rows = []
    strains = np.linspace(0, 0.02 if SHORT else 0.03, 5 if SHORT else 13)[1:]
    t0 = time.process_time()
    for strain in strains:
        drive.value = -strain * 2 * w
        its = p.solve()
        stress = -p.reaction(top, "u_z") / w**2
        rows.append({"axial_strain": float(strain), "mean_axial_stress": stress,
                     "newton_iterations": its})
    yielding = p.state.owned("yielding").reshape(-1, 3)
    fractions = [comm.allreduce(float(yielding[:, k].sum()), MPI.SUM)
                 / comm.allreduce(len(yielding), MPI.SUM) for k in range(3)]
    return {"length": length, "tau7": mu * length**2, "path": rows, "model": p.model.name,
            "cpu_s": comm.allreduce(time.process_time() - t0, MPI.SUM),
            "peak": max(r["mean_axial_stress"] for r in rows),
            "yielding_fraction_macro_micro_gradient": fractions,
            "dofs": int(p.V.dofmap.index_map.size_global * p.V.dofmap.index_map_bs)}


timings = {"start": time.perf_counter()}
homogeneous = [triaxial(s3) for s3 in confinements]
timings["homogeneous"] = time.perf_counter()
micro = micro_triaxial(100e3)
timings["micro_level"] = time.perf_counter()
rough = [platens(length) for length in args.lengths]
timings["rough_platens"] = time.perf_counter()


# ---- 4. coupled moduli: the return at the points -------------------------------------------
def coupled_elastic(length):
    """The decoupled set with the D-coupling (tau, sigma) and five more taus switched on."""
    l2 = mu * length**2
    return replace(elastic(length), tau=0.1 * mu, sigma=0.075 * mu, tau1=0.1 * l2,
                   tau2=0.05 * l2, tau4=0.1 * l2, tau8=0.05 * l2, tau11=0.02 * l2)


length = args.lengths[1]
iterative = {
    # the closed-form model and the iterative one on the decoupled set, at the quadrature
    # degree the iterative one is run with (its tangent is 45 x 45 per point)
    "closed_form_decoupled": platens(length, name="cf", quadrature_degree=2),
    "iterative_decoupled": platens(length, name="itd", quadrature_degree=2,
                                   model=MicromorphicDruckerPragerIterative(material(length))),
    "iterative_coupled": platens(length, name="itc", quadrature_degree=2,
                                 model=MicromorphicDruckerPragerIterative(
                                     replace(material(length), elastic=coupled_elastic(length)))),
}
decoupled_gap = max(abs(a["mean_axial_stress"] / b["mean_axial_stress"] - 1) for a, b in zip(
    iterative["closed_form_decoupled"]["path"], iterative["iterative_decoupled"]["path"], strict=True))
timings["coupled_moduli"] = time.perf_counter()
elapsed = timings["coupled_moduli"] - timings["start"]
marks = list(timings.values())
timings = {k: b - a for k, a, b in zip(list(timings)[1:], marks[:-1], marks[1:], strict=True)}

results = {
    "inputs": {"lam": lam, "mu": mu, "eta": 0.25 * mu, "kappa": 0.75 * mu, "nu": 0.15 * mu,
               "tau7": "mu l^2", "cohesion": c, "gradient_cohesion": "c l", "friction_deg": phi_f,
               "dilatancy_deg": psi, "match": "triaxial_compression", "confinements": confinements,
               "width": args.width, "lengths": list(args.lengths), "cells": cells,
               "degree": [2, 1], "short": SHORT, "ranks": comm.size},
    "homogeneous": homogeneous,
    "micro_level": micro,
    "rough_platens": rough,
    "coupled_moduli": {
        "length": length, "quadrature_degree": 2,
        "coupled_constants": {k: getattr(coupled_elastic(length), k)
                              for k in ("tau", "sigma", "tau1", "tau2", "tau4", "tau8", "tau11")},
        "runs": iterative,
        "max_rel_gap_iterative_vs_closed_form_decoupled": decoupled_gap,
    },
    "max_rel_error_peak_macro": max(h["rel_error_peak"] for h in homogeneous),
    "rel_error_peak_micro": micro["rel_error_peak"],
    "time_s": elapsed,
    "time_s_by_part": timings,
    "references": [
        "Regueiro 2009, Finite strain micromorphic pressure-sensitive plasticity, J. Eng. Mech. "
        "135(3) (a Drucker-Prager cone on each level, non-associated flow)",
        "Regueiro 2010, On finite strain micromorphic elastoplasticity, IJSS 47 (the relative "
        "stress Sigma - S of the micro level, one higher-order yield function per slice M)",
        "Mohr-Coulomb triaxial compression: sigma_1 = sigma_3 tan^2(45 + phi/2) + 2 c tan(45 + phi/2)",
    ],
}

if comm.rank == 0:
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    for h in homogeneous:
        print(f"macro sigma3 {h['sigma3'] / 1e3:.0f} kPa: peak {h['peak']:.8g} Pa, Mohr-Coulomb "
              f"{h['mohr_coulomb']:.8g} (rel {h['rel_error_peak']:.1e}); dilatancy "
              f"{h['dilatancy_ratio']:.6f} (flow rule {h['dilatancy_ratio_flow_rule']:.6f}); "
              f"unloading modulus {h['unloading_modulus']:.6g} (E {young:.6g})")
    print(f"micro level sigma3 100 kPa: peak {micro['peak']:.8g} Pa (rel {micro['rel_error_peak']:.1e})")
    for r in rough:
        print(f"rough platens l = {r['length'] * 1e3:.1f} mm: peak mean axial stress "
              f"{r['peak']:.6g} Pa ({r['peak'] / mohr_coulomb_peak(100e3):.4f} x homogeneous); "
              f"yielding fractions {np.round(r['yielding_fraction_macro_micro_gradient'], 3).tolist()}; "
              f"Newton {[row['newton_iterations'] for row in r['path']]}")
    for key, r in iterative.items():
        print(f"platens l = {length * 1e3:g} mm, {key}: peak {r['peak']:.6g} Pa, Newton "
              f"{[row['newton_iterations'] for row in r['path']]}, {r['cpu_s']:.1f} s CPU")
    print(f"iterative against closed-form return (decoupled moduli): {decoupled_gap:.1e}")
    print(f"{elapsed:.1f} s ({', '.join(f'{k} {v:.1f} s' for k, v in timings.items())}); "
          f"outputs in {args.out}")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    for h in homogeneous:
        e = [r["axial_strain"] * 100 for r in h["path"]]
        ax1.plot(e, [r["axial_stress"] / 1e3 for r in h["path"]], "o-", ms=3,
                 label=f"$\\sigma_3$ = {h['sigma3'] / 1e3:.0f} kPa")
        ax1.axhline(h["mohr_coulomb"] / 1e3, color="k", lw=0.6, ls=":")
    e = [-r["phi_zz"] * 100 for r in micro["path"]]
    ax1.plot(e, [-r["relative_stress_zz"] / 1e3 for r in micro["path"]], "s--", ms=3,
             label="micro level, $\\sigma_3$ = 100 kPa")
    ax1.set_xlabel("axial strain (micro: $-\\phi_{zz}$) [%]")
    ax1.set_ylabel("axial stress [kPa]")
    ax1.set_title("homogeneous: peaks on Mohr-Coulomb (dotted)")
    ax1.legend(fontsize=8)
    for r in rough:
        ax2.plot([row["axial_strain"] * 100 for row in r["path"]],
                 [row["mean_axial_stress"] / 1e3 for row in r["path"]], "o-", ms=3,
                 label=f"rough platens, l = {r['length'] * 1e3:g} mm")
    r = iterative["iterative_coupled"]
    ax2.plot([row["axial_strain"] * 100 for row in r["path"]],
             [row["mean_axial_stress"] / 1e3 for row in r["path"]], "s--", ms=3,
             label=f"l = {length * 1e3:g} mm, coupled moduli (return at the points)")
    ax2.axhline(mohr_coulomb_peak(100e3) / 1e3, color="k", lw=0.6, ls=":", label="homogeneous peak")
    ax2.set_xlabel("axial strain [%]")
    ax2.set_ylabel("mean axial stress [kPa]")
    ax2.set_title("prism between rough platens, $\\sigma_3$ = 100 kPa")
    ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "micromorphic_plastic_triaxial.png", dpi=110)

# ---- checks ---------------------------------------------------------------------------------
for h in homogeneous:
    assert h["rel_error_peak"] < 1e-8, h["rel_error_peak"]
    assert abs(h["dilatancy_ratio"] / h["dilatancy_ratio_flow_rule"] - 1) < 1e-8
    assert abs(h["unloading_modulus"] / young - 1) < 1e-8
assert micro["rel_error_peak"] < 1e-8
for r in rough:
    assert r["peak"] > mohr_coulomb_peak(100e3) * (1 - 1e-6)    # the platens only add restraint
assert rough[1]["peak"] > rough[0]["peak"]                       # larger l, stiffer and stronger
assert decoupled_gap < 1e-8                                      # the same returns, two ways
