"""Cost of a plastic 3D load step against an elastic one on the same calibration-chamber mesh.

The 3D chamber of the penetration scenes (cylinder of radius R and depth H, refined toward
the DE window on the axis, :func:`meshes.penetration.build_chamber`) carries gravity, then a
rough rigid punch (radius 3 cm, half the window's) is pushed into its surface in ``--steps`` equal
displacement steps, once with the micropolar elastic model and once with the micropolar
Drucker-Prager model of the same elasticity (the cone matched to triaxial compression), on
the same mesh, with the same solver (SNES, MUMPS LU unless ``--solver``). The punch is pushed
far enough that the plastic zone under it holds a sizeable share of the quadrature points.

Measured per mesh size and model, ``--repeat`` times (fresh problems, forms compiled by a
warm-up run first): the wall time of each load step, its Newton iterations, and the time of
the whole path. The plastic path is run four times, each adding one change to the last:

- ``plastic_trial_tangent``: the model as it was (``tangent_predictor = False``): Newton's
  first iteration of a step took the tangent of the trial return, elastic at every yielding
  point whose trial value round-off put below the cone (about half of them);
- ``plastic``: the model now: those points take the elastic-plastic tangent of the last
  converged step (the tangent predictor, :meth:`MicropolarDruckerPrager._return`);
- ``plastic_secant_tol``: Newton starts from the secant predictor (the last two converged
  states extrapolated) and stops at ``--load-tol`` (1e-8) of the norm of the load increment's
  residual (the residual of the new loads on the last converged state, one residual
  assembly), instead of 1e-10 of the step's own first residual (which a good predictor makes
  small, so that it asked for more): ``granfe.stepping.StepControl(predictor="secant",
  load_tol=...)``;
- ``plastic_secant_tol_one_lu``: one LU factorisation a step: the tangent of the step's first
  iteration preconditions GMRES on the assembled tangent of the later iterations (PETSc's
  ``snes_lag_preconditioner``, reset at every solve; Newton's iterates are unchanged):
  ``granfe.solvers.ONE_LU_PER_STEP``.

The punch force at the end is recorded for each (they agree to 9 digits). Not taken: a lower
quadrature degree (for P1/P1 the return is the same at the 4 points of a tetrahedron, but one
point under-integrates the elastic skew term: the tangent assembles 2x faster, the punch force
moves by 0.75 %), other MUMPS orderings (METIS / AMF / AMD within the noise; the symbolic
factorisation is already done once per problem). ``results.json``: per mesh the dofs, the step
times (min and median over steps and repeats), the path times (min and median over
repeats), the Newton iterations per step, the share of yielding points at the end, and the
ratios plastic / elastic of the median path times (wall and CPU); the CPU model from ``/proc/cpuinfo``.

Run: ``python benchmarks/plastic_cost.py`` (serial; ``--h-window 0.02 0.01`` for about 10 min on
the 2-core VM beside other jobs).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
from machine import cpu_model

from granfe.materials import MicropolarMaterial
from granfe.models.drucker_prager import DruckerPragerMaterial, MicropolarDruckerPrager
from granfe.models.micropolar import Micropolar
from granfe.probe import probe
from granfe.problem import ContinuumProblem
from granfe.solvers import ONE_LU_PER_STEP
from granfe.stepping import StepControl, follow_load_path
from meshes.penetration import build_chamber

SHORT = os.environ.get("GRANFE_SHORT") == "1"
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--h-window", type=float, nargs="+", default=[0.02] if SHORT else [0.02, 0.01, 0.006],
                    help="element sizes in the window [m] (one mesh each)")
parser.add_argument("--h-far", type=float, default=0.05, help="element size far from it [m]")
parser.add_argument("--degree", type=int, nargs=2, default=(1, 1),
                    help="degrees of u and phi (the coupled scenes use 1 1)")
parser.add_argument("--steps", type=int, default=4 if SHORT else 6, help="load steps of the punch")
parser.add_argument("--settlement", type=float, default=2e-4, help="final punch settlement [m]")
parser.add_argument("--repeat", type=int, default=1 if SHORT else 3)
parser.add_argument("--load-tol", type=float, default=1e-8,
                    help="Newton tolerance of the *_tol variants, relative to the load increment's residual")
parser.add_argument("--solver", choices=("direct", "iterative"), default="direct")
parser.add_argument("--out", type=Path, default=Path("output/plastic_cost"))
args = parser.parse_args()
comm = MPI.COMM_WORLD

# ---- the chamber and the soil (SI) --------------------------------------------------------
R, H = 0.15, 0.2                  # chamber radius and depth [m], as scenes/cpt_3d.toml
window_radius, window_depth = 0.06, 0.08
punch_radius = 0.03               # the rough punch on the surface [m]
rho, g = 1600.0, 9.81             # bulk density [kg/m^3], gravity [m/s^2]
E, nu = 5e6, 0.3
cohesion, friction, dilatancy = 500.0, 30.0, 5.0      # [Pa], [deg], [deg]
G = E / (2 * (1 + nu))
kappa, length = 0.5 * G, 4e-3     # coupling modulus [Pa]; Cosserat length ~ a grain diameter [m]
elastic = MicropolarMaterial(lam=E * nu / ((1 + nu) * (1 - 2 * nu)), mu=G - kappa / 2, kappa=kappa,
                             gamma=2 * G * length**2, rho=rho, j=length**2)
plastic = DruckerPragerMaterial(elastic, cohesion, friction, dilatancy, match="triaxial_compression")




def log(msg):
    if comm.rank == 0:
        print(msg, flush=True)


def chamber(h_window: float):
    data = build_chamber(comm, 3, radius=R, depth=H, window_radius=window_radius,
                         window_depth=window_depth, h_window=h_window, h_far=args.h_far)
    names = {k: tag for k, (d, tag) in data.physical_groups.items() if d == 2}
    return data, names


def under_punch(x):
    return np.isclose(x[2], 0.0) & (np.hypot(x[0], x[1]) <= punch_radius + 1e-9)


def push(data, names, variant: Variant, tag: str) -> dict:
    """Gravity, then the punch in ``args.steps`` steps; the step times and iterations."""
    model = variant.model(variant.material)
    problem = ContinuumProblem(data.mesh, model, facet_tags=data.facet_tags, tag_names=names,
                               degree=tuple(args.degree), solver=args.solver, prefix=f"cost_{tag}_",
                               petsc_options=variant.options)
    problem.fix("bottom", "u")
    problem.fix("bottom", "phi")
    problem.fix("side", "u_x")
    problem.fix("side", "u_y")
    problem.body_force((0.0, 0.0, -rho * g))
    problem.solve()                                   # geostatic: elastic for both models
    top = probe(problem.w.sub(0).collapse(), np.zeros((1, 3)))[0]
    for c, v in zip(("u_x", "u_y"), top[:2], strict=True):
        problem.fix(under_punch, c, float(v))       # rough, from where gravity left it
    settle = problem.fix(under_punch, "u_z", float(top[2]))
    problem.solve()                                   # builds the solver (not timed)
    # equal steps (a failed one ends the path); the secant predictor and the load tolerance
    # are granfe.stepping's
    h = args.settlement / args.steps
    control = StepControl(first=h, min_step=h, max_step=h, predictor="secant" if variant.secant else "last",
                          load_tol=variant.load_tol)
    times, cpu, its, start = [], [], [], [0.0, 0.0]

    def apply(t):
        settle.value = top[2] - t
        comm.barrier()
        start[:] = time.perf_counter(), time.process_time()

    def record(t, n):
        times.append(time.perf_counter() - start[0])
        cpu.append(time.process_time() - start[1])
        its.append(n)

    follow_load_path(problem, apply, args.settlement, control, on_step=record)
    force = -problem.reaction(under_punch, "u_z")   # the punch force at the end [N]
    yielding = problem.state.owned("yielding") if problem.state else np.zeros(0)
    share = comm.allreduce(float(yielding.sum()), MPI.SUM) / max(comm.allreduce(yielding.size, MPI.SUM), 1)
    return {"step_s": times, "step_cpu_s": cpu, "newton_iterations": its, "path_s": float(sum(times)),
            "path_cpu_s": float(sum(cpu)), "punch_force": force,
            "yielding_share": share,
            "dofs": problem.V.dofmap.index_map.size_global * problem.V.dofmap.index_map_bs}


def summarise(runs: list[dict]) -> dict:
    out = {}
    for clock in ("s", "cpu_s"):        # wall and CPU (process) time
        steps = np.concatenate([r[f"step_{clock}"] for r in runs])
        paths = np.array([r[f"path_{clock}"] for r in runs])
        out.update({f"step_{clock}_min": float(steps.min()), f"step_{clock}_median": float(np.median(steps)),
                    f"path_{clock}_min": float(paths.min()), f"path_{clock}_median": float(np.median(paths))})
    return {**out, "newton_iterations": runs[-1]["newton_iterations"],
            "newton_iterations_mean": float(np.mean(runs[-1]["newton_iterations"])),
            "yielding_share": runs[-1]["yielding_share"], "punch_force": runs[-1]["punch_force"],
            "step_s_last_repeat": runs[-1]["step_s"]}


class TrialTangent(MicropolarDruckerPrager):
    """The model as it was: Newton's first iteration takes the tangent of the trial return,
    elastic at the yielding points whose trial value round-off puts below the cone."""

    tangent_predictor = False


@dataclass(frozen=True)
class Variant:
    """model: class; secant: start Newton from the last two converged states extrapolated;
    load_tol: converge at this fraction of the norm of the load increment's residual (the
    first residual of a step started from the last converged state) instead of the default
    1e-10 of the step's own first residual; options: PETSc options."""

    model: type
    material: object
    secant: bool = False
    load_tol: float | None = None
    options: dict = field(default_factory=dict)


LOAD_TOL = args.load_tol
VARIANTS = {"elastic": Variant(Micropolar, elastic),
            "plastic_trial_tangent": Variant(TrialTangent, plastic),
            "plastic": Variant(MicropolarDruckerPrager, plastic),
            "plastic_secant_tol": Variant(MicropolarDruckerPrager, plastic, True, LOAD_TOL),
            "plastic_secant_tol_one_lu": Variant(MicropolarDruckerPrager, plastic, True, LOAD_TOL, ONE_LU_PER_STEP)}
PLASTIC = [k for k in VARIANTS if k != "elastic"]

# ---- measure ---------------------------------------------------------------------------
results = {"what": "wall time of a 3D load step of the calibration chamber (gravity, then a rough "
                   "punch), micropolar Drucker-Prager against micropolar elastic on the same mesh",
           "inputs": {"chamber": [R, H], "window": [window_radius, window_depth],
                      "punch_radius": punch_radius, "h_far": args.h_far, "degree": list(args.degree),
                      "steps": args.steps, "settlement": args.settlement, "repeat": args.repeat,
                      "solver": args.solver, "E": E, "nu": nu, "kappa": kappa, "length": length,
                      "cohesion": cohesion, "friction_deg": friction, "dilatancy_deg": dilatancy,
                      "match": "triaxial_compression", "density": rho, "ranks": comm.size,
                      "short": SHORT},
           "cpu": cpu_model(), "meshes": []}
data, names = chamber(max(args.h_window))
for name, variant in VARIANTS.items():                                    # compile every form once
    push(data, names, variant, f"warm_{name}")
for h in args.h_window:
    data, names = chamber(h)
    entry = {"h_window": h, "cells": comm.allreduce(data.mesh.topology.index_map(3).size_local, MPI.SUM)}
    for rep in range(args.repeat):
        for name, variant in VARIANTS.items():                                 # interleaved: a
            entry.setdefault(name, []).append(                                   # busy spell hits
                push(data, names, variant, f"{name}{rep}_{h:g}"))                # all
    for name in VARIANTS:
        entry["dofs"] = entry[name][-1]["dofs"]
        entry[name] = summarise(entry[name])
    for name in PLASTIC:
        entry[f"{name}_over_elastic"] = entry[name]["path_s_median"] / entry["elastic"]["path_s_median"]
        entry[f"{name}_over_elastic_cpu"] = (entry[name]["path_cpu_s_median"]
                                             / entry["elastic"]["path_cpu_s_median"])
    results["meshes"].append(entry)
    log(f"h {h:g}: {entry['dofs']} dofs, {entry['cells']} cells; elastic path "
        f"{entry['elastic']['path_cpu_s_median']:.2f} s CPU; yielding "
        f"{100 * entry['plastic']['yielding_share']:.0f} % of the points at the end")
    for name in PLASTIC:
        log(f"  {name}: x {entry[f'{name}_over_elastic_cpu']:.2f} CPU, x "
            f"{entry[f'{name}_over_elastic']:.2f} wall, Newton its {entry[name]['newton_iterations']}, "
            f"punch force {entry[name]['punch_force']:.9g} N")

if comm.rank == 0:
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
for entry in results["meshes"]:
    assert entry["plastic"]["yielding_share"] > 0.01, "the punch did not yield the soil"
    assert all(i == 1 for i in entry["elastic"]["newton_iterations"])
