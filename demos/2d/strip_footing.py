"""Bearing capacity of a rigid rough strip footing on a micropolar Drucker-Prager layer.

This demo shows how to:

- build a plastic continuum from the model registry (micropolar Drucker-Prager, the cone
  matched to Mohr-Coulomb in plane strain, associated flow) on gmsh meshes refined at the
  footing's edge,
- push a rigid rough footing down under displacement control with automatic load-step
  cut-back (:func:`granfe.stepping.follow_load_path`),
- compare the collapse pressure on a weightless cohesive-frictional layer with Prandtl's
  ``q_u = c N_c``, ``N_c = (N_q - 1) cot phi``, ``N_q = exp(pi tan phi) tan^2(45 + phi/2)``
  (``N_c = 2 + pi`` for phi = 0), on a sequence of meshes refined at the edge,
- write the load-settlement curves, the convergence of the collapse load, the equivalent
  plastic strain of the finest mesh (VTX and PNG).

What limits the finite-element collapse load (measured, P2, phi = 0, the edge element
``b/20 .. b/320``): the stress and velocity singularity at the footing's edge, where the
Prandtl fan is centred (+9.9 / +6.7 / +4.5 / +3.0 / +2.3 % at b/20 / 40 / 80 / 160 / 320:
the excess falls like ``h_edge^0.57``, then 0.40); the Cosserat plastic length (at 1 % of
the width it added 1.1 % at b/160, so it is 0.1 % here: the continuum is then classical at
these meshes); the layer for phi > 0 (the
Prandtl mechanism reaches ``b + 2 r_1 cos(45 - phi/2)`` from the axis, 6.1 b for phi = 20,
so the layer is 1.25 times that); the far element size (b/4 -> b/8: -0.5 %). Not limiting:
the quadrature degree of the plastic forms (degree 2 and 4 give the same load to 4 digits
with P2: degree 2, the exact one for the elastic P2 stiffness, is used), the load step at
the limit (the curve's last fifth moves by < 0.3 %). The collapse load is the pressure at
the final settlement; a Richardson extrapolation of the last three meshes is stated beside
it, not used for the checks. phi = 20 converges more slowly (+8.3 / +6.0 / +4.4 / +3.3 /
+2.9 % at b/20 / 40 / 80 / 160 / 320, separate runs; ~500 load steps of 8-9 Newton
iterations each, 5-16 min a mesh on the shared 2-core VM): only phi = 0 is checked
against 3 %.

Run: ``python demos/2d/strip_footing.py [--friction 0 20 --h-edge 0.05 0.025 0.0125]`` (the
default: phi = 0 and 20, edge b/20 .. b/320).
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
parser.add_argument("--h-edge", type=float, nargs="+", default=None,
                    help="element sizes at the edge [m] (one mesh each, coarse to fine)")
parser.add_argument("--h-far", type=float, default=None, help="element size away from it [m]")
parser.add_argument("--settlement", type=float, default=None,
                    help="final settlement [m] (default 0.02 b for phi = 0, more with friction)")
parser.add_argument("--degree", type=int, nargs=2, default=(2, 1), help="degrees of u and phi")
parser.add_argument("--quadrature-degree", type=int, default=None,
                    help="of the plastic forms (default 2 (p_u - 1), exact for the elastic stiffness)")
parser.add_argument("--plastic-length", type=float, default=0.001,
                    help="Cosserat plastic length as a fraction of the footing width 2b")
parser.add_argument("--out", type=Path, default=Path("output/strip_footing"))
args = parser.parse_args()
comm = MPI.COMM_WORLD

b = args.half_width
h_edges = args.h_edge or ([b / 8] if SHORT else [b / 20, b / 40, b / 80, b / 160, b / 320])
h_far = args.h_far or (b / 2 if SHORT else b / 4)
frictions = args.friction[:1] if SHORT else args.friction
l_plastic = args.plastic_length * (2 * b)        # Cosserat plastic length
qdeg = args.quadrature_degree or 2 * (args.degree[0] - 1)


def prandtl_nc(phi_deg: float) -> float:
    if phi_deg == 0:
        return 2 + math.pi
    t = math.tan(math.radians(phi_deg))
    nq = math.exp(math.pi * t) * math.tan(math.radians(45 + phi_deg / 2)) ** 2
    return (nq - 1) / t


def layer(phi_deg: float) -> tuple[float, float]:
    """Width and depth of the half layer: 1.25 times the reach of Prandtl's mechanism (the
    passive wedge's far end, ``b + 2 r_1 cos(45 - phi/2)``; the log spiral's radius ``r_1``
    for the depth), at least 6 b x 4 b."""
    phi = math.radians(phi_deg)
    r0 = b / math.cos(math.pi / 4 + phi / 2)
    r1 = r0 * math.exp(math.pi / 2 * math.tan(phi))
    reach = b + 2 * r1 * math.cos(math.pi / 4 - phi / 2)
    return max(6 * b, math.ceil(1.25 * reach / b) * b), max(4 * b, math.ceil(1.25 * r1 / b) * b)


def log(msg):
    if comm.rank == 0:
        print(msg, flush=True)


# ---- set-up ---------------------------------------------------------------------------
lam = args.E * args.nu / ((1 + args.nu) * (1 - 2 * args.nu))
G = args.E / (2 * (1 + args.nu))
kappa = 0.5 * G                                   # coupling modulus; G = mu + kappa / 2
elastic = MicropolarMaterial(lam=lam, mu=G - kappa / 2, kappa=kappa,
                             gamma=2 * G * l_plastic**2, j=l_plastic**2)
args.out.mkdir(parents=True, exist_ok=True)
results = {"inputs": {"half_width": b, "E": args.E, "nu": args.nu, "cohesion": args.cohesion,
                      "h_edge": h_edges, "h_far": h_far, "plastic_length": l_plastic,
                      "degree": list(args.degree), "quadrature_degree": qdeg, "short": SHORT,
                      "ranks": comm.size},
           "cases": []}

def collapse(phi: float, h_edge: float, write: bool) -> dict:
    """Push the footing to a settlement past collapse on a layer of friction angle phi."""
    W, D = layer(phi)
    data = footing.build(comm, b, W, D, h_edge, h_far)
    names = {name: tag for name, (dim, tag) in data.physical_groups.items() if dim == 1}
    material = DruckerPragerMaterial(elastic, args.cohesion, phi, phi, match="plane_strain")
    model = model_class("micropolar_drucker_prager")(material)
    problem = ContinuumProblem(data.mesh, model, facet_tags=data.facet_tags, tag_names=names,
                               degree=tuple(args.degree), quadrature_degree=qdeg,
                               prefix=f"footing{int(phi)}_{h_edge:g}_")
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
        log(f"  phi {phi:4.1f}, h_edge {h_edge:g}: settlement {t * 1e3:7.3f} mm  q/c {q / args.cohesion:7.3f} "
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
    if write:
        with ContinuumWriter(problem, args.out, name=f"footing_phi{int(phi)}") as writer:
            writer.write(final)
    case = {"friction_deg": phi, "h_edge": h_edge, "layer": [W, D],
            "N_c_prandtl": prandtl_nc(phi), "q_u_prandtl": q_ref,
            "q_collapse": q_last, "N_c_fe": q_last / args.cohesion,
            "error": q_last / q_ref - 1, "plateau_spread": plateau, "steps": len(curve),
            "newton_iterations": int(sum(i for _, _, i in curve)), "wall_s": wall,
            "dofs": problem.V.dofmap.index_map.size_global,
            "curve": [[t, q] for t, q, _ in curve]}
    log(f"phi = {phi}, h_edge = {h_edge:g}: q/c = {q_last / args.cohesion:.3f} against Prandtl {prandtl_nc(phi):.3f} "
        f"({100 * case['error']:+.1f} %), plateau spread {100 * plateau:.2f} %, {wall:.1f} s")
    return case


# ---- solve ----------------------------------------------------------------------------
results["cases"] = [collapse(phi, h, write=h == h_edges[-1]) for phi in frictions for h in h_edges]


def richardson(cases: list[dict]) -> dict | None:
    """Limit of the last three meshes (edge sizes halving) for ``q = q_0 + C h^p``."""
    if len(cases) < 3:
        return None
    q1, q2, q3 = (c["q_collapse"] for c in cases[-3:])
    h1, h2, h3 = (c["h_edge"] for c in cases[-3:])
    if not (np.isclose(h1 / h2, h2 / h3) and (q1 - q2) * (q2 - q3) > 0):
        return None
    rate = math.log((q1 - q2) / (q2 - q3)) / math.log(h1 / h2)
    q0 = q3 - (q2 - q3) / ((h2 / h3) ** rate - 1)
    return {"rate": rate, "q_extrapolated": q0, "N_c_extrapolated": q0 / args.cohesion}


results["convergence"] = []
for phi in frictions:
    cases = [c for c in results["cases"] if c["friction_deg"] == phi]
    entry = {"friction_deg": phi, "h_edge": [c["h_edge"] for c in cases],
             "dofs": [c["dofs"] for c in cases], "error": [c["error"] for c in cases],
             "richardson": richardson(cases)}
    if entry["richardson"]:
        entry["richardson"]["error"] = entry["richardson"]["q_extrapolated"] / cases[0]["q_u_prandtl"] - 1
    results["convergence"].append(entry)
    log(f"phi = {phi}: error " + ", ".join(f"{100 * e:+.2f} % (b/{b / h:.0f})"
                                         for e, h in zip(entry["error"], entry["h_edge"], strict=True))
        + (f"; Richardson {100 * entry['richardson']['error']:+.2f} % (rate "
           f"{entry['richardson']['rate']:.2f})" if entry["richardson"] else ""))

# ---- plots and checks -----------------------------------------------------------------
if comm.rank == 0:
    import matplotlib
    import matplotlib.ticker
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    for case in results["cases"]:
        if case["h_edge"] != h_edges[-1]:
            continue
        t, q = np.array(case["curve"]).T
        line, = ax.plot(t / b, q / args.cohesion,
                        label=f"FE, phi = {case['friction_deg']:g}, h_edge = b/{b / case['h_edge']:.0f}")
        ax.axhline(case["N_c_prandtl"], ls="--", color=line.get_color(),
                   label=f"Prandtl N_c = {case['N_c_prandtl']:.2f}")
    ax.set_xlabel("settlement / b")
    ax.set_ylabel("mean footing pressure / c")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    for entry in results["convergence"]:
        h = np.array(entry["h_edge"]) / b
        ax2.loglog(h, 100 * np.abs(entry["error"]), "o-", label=f"phi = {entry['friction_deg']:g}")
    ax2.axhline(3.0, ls=":", color="grey", label="3 %")
    ax2.set_xticks([h / b for h in h_edges], [f"b/{b / h:.0f}" for h in h_edges])
    ax2.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax2.yaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    ax2.yaxis.set_minor_formatter(matplotlib.ticker.ScalarFormatter())
    ax2.set_xlabel("element size at the footing's edge / b")
    ax2.set_ylabel("collapse load above Prandtl [%]")
    ax2.legend(fontsize=8)
    ax2.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(args.out / "load_settlement.png", dpi=120)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))

for case in results["cases"]:                     # a kinematic bound: from above
    assert -0.02 < case["error"] < 0.25, case["error"]
if not SHORT:                                     # converging; phi = 0 within 3 % at b/160
    for entry in results["convergence"]:         # (phi = 20: +2.9 % at b/320, barely)
        assert np.all(np.diff(entry["error"]) < 0), entry["error"]
        if entry["friction_deg"] == 0 and entry["h_edge"][-1] <= b / 160:
            assert entry["error"][-1] < 0.03, entry["error"]
