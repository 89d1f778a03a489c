"""Bearing capacity of a rigid rough strip footing on a micropolar Drucker-Prager layer.

This demo shows how to:

- build a plastic continuum from the model registry (micropolar Drucker-Prager, the cone
  matched to Mohr-Coulomb in plane strain, associated flow) on a gmsh mesh refined at the
  footing's edge,
- push a rigid rough footing down under displacement control with automatic load-step
  cut-back (:func:`granfe.stepping.follow_load_path`),
- compare the collapse pressure on a weightless cohesive-frictional layer with Prandtl's
  ``q_u = c N_c``, ``N_c = (N_q - 1) cot phi``, ``N_q = exp(pi tan phi) tan^2(45 + phi/2)``
  (``N_c = 2 + pi`` for phi = 0),
- write the load-settlement curves, the equivalent plastic strain (VTX and PNG).

The plastic length of the Cosserat continuum is 1 % of the footing width, so the collapse
load is the classical one; a finite-element limit load approaches it from above as the
mesh is refined.

Run: ``mpiexec -n 2 python demos/2d/strip_footing.py [--friction 0 20 --h-edge 0.025]``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np

from granfe.io import ContinuumWriter
from granfe.materials import MicropolarMaterial
from granfe.models import model_class
from granfe.models.drucker_prager import DruckerPragerMaterial
from granfe.problem import ContinuumProblem
from granfe.stepping import StepControl, follow_load_path
from meshes import footing

SHORT = os.environ.get("GRANFE_SHORT") == "1"

# ---- parameters (SI) ------------------------------------------------------------------
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--half-width", type=float, default=1.0, help="footing half-width b [m]")
parser.add_argument("--E", type=float, default=1.0e8, help="Young's modulus [Pa]")
parser.add_argument("--nu", type=float, default=0.3, help="Poisson's ratio")
parser.add_argument("--cohesion", type=float, default=1.0e4, help="c [Pa]")
parser.add_argument("--friction", type=float, nargs="+", default=[0.0, 20.0],
                    help="friction angles phi [deg] (one run each, associated flow)")
parser.add_argument("--h-edge", type=float, default=None, help="element size at the edge [m]")
parser.add_argument("--h-far", type=float, default=None, help="element size away from it [m]")
parser.add_argument("--settlement", type=float, default=None,
                    help="final settlement [m] (default 0.02 b for phi = 0, more with friction)")
parser.add_argument("--degree", type=int, nargs=2, default=(2, 1), help="degrees of u and phi")
parser.add_argument("--out", type=Path, default=Path("output/strip_footing"))
args = parser.parse_args()
comm = MPI.COMM_WORLD

b = args.half_width
W, D = 6 * b, 4 * b
h_edge = args.h_edge or (b / 8 if SHORT else b / 40)
h_far = args.h_far or (b / 2 if SHORT else b / 4)
frictions = args.friction[:1] if SHORT else args.friction
l_plastic = 0.01 * (2 * b)                       # Cosserat plastic length: 1 % of the width


def prandtl_nc(phi_deg: float) -> float:
    if phi_deg == 0:
        return 2 + math.pi
    t = math.tan(math.radians(phi_deg))
    nq = math.exp(math.pi * t) * math.tan(math.radians(45 + phi_deg / 2)) ** 2
    return (nq - 1) / t


def log(msg):
    if comm.rank == 0:
        print(msg, flush=True)


# ---- set-up ---------------------------------------------------------------------------
data = footing.build(comm, b, W, D, h_edge, h_far)
names = {name: tag for name, (dim, tag) in data.physical_groups.items() if dim == 1}
lam = args.E * args.nu / ((1 + args.nu) * (1 - 2 * args.nu))
G = args.E / (2 * (1 + args.nu))
kappa = 0.5 * G                                   # coupling modulus; G = mu + kappa / 2
elastic = MicropolarMaterial(lam=lam, mu=G - kappa / 2, kappa=kappa,
                             gamma=2 * G * l_plastic**2, j=l_plastic**2)
args.out.mkdir(parents=True, exist_ok=True)
results = {"inputs": {"half_width": b, "E": args.E, "nu": args.nu, "cohesion": args.cohesion,
                      "layer": [W, D], "h_edge": h_edge, "h_far": h_far,
                      "plastic_length": l_plastic, "degree": list(args.degree), "short": SHORT,
                      "ranks": comm.size},
           "cases": []}

def collapse(phi: float) -> dict:
    """Push the footing to a settlement past collapse on a layer of friction angle phi."""
    material = DruckerPragerMaterial(elastic, args.cohesion, phi, phi, match="plane_strain")
    model = model_class("micropolar_drucker_prager")(material)
    problem = ContinuumProblem(data.mesh, model, facet_tags=data.facet_tags, tag_names=names,
                               degree=tuple(args.degree), prefix=f"footing{int(phi)}_")
    problem.fix("symmetry", "u_x")
    problem.fix("symmetry", "phi")
    problem.fix("bottom", "u")
    problem.fix("right", "u_x")
    problem.fix("footing", "u_x")                 # rough
    problem.fix("footing", "phi")                 # rigid
    settle = problem.fix("footing", "u_y", 0.0)
    final = args.settlement or (0.02 if phi == 0 else 0.02 * (1 + phi / 10)) * b
    q_ref = args.cohesion * prandtl_nc(phi)
    curve = []

    def record(t, its):
        q = -problem.reaction("footing", "u_y") / b       # mean pressure under the footing
        curve.append((t, q, its))
        log(f"  phi {phi:4.1f}: settlement {t * 1e3:7.3f} mm  q/c {q / args.cohesion:7.3f} "
            f"({its} Newton its)")

    t0 = time.perf_counter()
    control = StepControl(first=final / 40, min_step=final / 5000, max_step=final / 10)
    follow_load_path(problem, lambda t: setattr(settle, "value", -t), final, control,
                     on_step=record, log=log)
    wall = time.perf_counter() - t0
    q_last = curve[-1][1]
    # the plateau: how much the last fifth of the curve still moves
    tail = [q for t, q, _ in curve if t >= 0.8 * final]
    plateau = (max(tail) - min(tail)) / q_last
    with ContinuumWriter(problem, args.out, name=f"footing_phi{int(phi)}") as writer:
        writer.write(final)
    case = {"friction_deg": phi, "N_c_prandtl": prandtl_nc(phi), "q_u_prandtl": q_ref,
            "q_collapse": q_last, "N_c_fe": q_last / args.cohesion,
            "error": q_last / q_ref - 1, "plateau_spread": plateau, "steps": len(curve),
            "newton_iterations": int(sum(i for _, _, i in curve)), "wall_s": wall,
            "dofs": problem.V.dofmap.index_map.size_global,
            "curve": [[t, q] for t, q, _ in curve]}
    log(f"phi = {phi}: q/c = {q_last / args.cohesion:.3f} against Prandtl {prandtl_nc(phi):.3f} "
        f"({100 * case['error']:+.1f} %), plateau spread {100 * plateau:.2f} %, {wall:.1f} s")
    return case


# ---- solve ----------------------------------------------------------------------------
results["cases"] = [collapse(phi) for phi in frictions]

# ---- plots and checks -----------------------------------------------------------------
if comm.rank == 0:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for case in results["cases"]:
        t, q = np.array(case["curve"]).T
        line, = ax.plot(t / b, q / args.cohesion, label=f"FE, phi = {case['friction_deg']:g}")
        ax.axhline(case["N_c_prandtl"], ls="--", color=line.get_color(),
                   label=f"Prandtl N_c = {case['N_c_prandtl']:.2f}")
    ax.set_xlabel("settlement / b")
    ax.set_ylabel("mean footing pressure / c")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(args.out / "load_settlement.png", dpi=120)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))

tolerance = 0.25 if SHORT else 0.08               # coarse meshes overestimate more
for case in results["cases"]:
    assert -0.02 < case["error"] < tolerance, case["error"]
