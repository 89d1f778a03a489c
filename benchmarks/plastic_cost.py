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

The dynamic case (``--cases dynamic``, recorded under ``"dynamic"``): the FE time step of the
coupled 3D calibration chamber (``scenes/chamber_3d.toml``'s box, its window refined to
``--dynamic-h``, its FE step of 10 DEM steps, generalized-alpha with rho_inf 0.8, the solver
``"redundant"`` and the Newton tolerance of the coupled run), the soil under 100 kPa with the
Drucker-Prager cone of the README's 3D plastic run, the top nodes within 12 mm of the axis
pushed down at the cone's speed (1 m/s) for ``--dynamic-steps`` steps, in place of the grains.
Variants: ``elastic`` (the affine step: one solve with the Jacobian factorised once),
``plastic_newton`` (Newton on the consistent tangent, the step as it was:
``GeneralizedAlpha(tangent="consistent")``), ``plastic_newton_one_lu`` (the same with
``ONE_LU_PER_STEP``), ``plastic_elastic_qn`` (quasi-Newton on the elastic Jacobian
factorised once for the run, the default now) and ``plastic_elastic_qn_tight`` (the same
stopped at a thousandth of the absolute tolerance, compared with ``plastic_newton_tight``,
Newton stopped there: the difference from Newton's answer is the tolerance's), and the explicit
steps (``elastic_explicit``, ``plastic_explicit``: :class:`granfe.explicit.CentralDifference`,
central differences on a lumped mass, the step split into substeps below the stability limit
it measures; the plastic one through the Drucker-Prager kernel that fuses the return with the
element forces: no solve). ``elastic_fine_dt`` / ``plastic_fine_dt``: the implicit step at an
eighth of dt (quasi-Newton at a thousandth of the tolerance), against which each variant's
time-discretisation error is read (``*_difference_vs_fine_dt``). Each set runs at every
``--dynamic-E`` (20 MPa: the affine constants' stiffness; 1.2 MPa: the window's probed in
situ, which the chamber runs now). Per variant
the step times (min and median over steps and repeats, wall and CPU), the iterations, the LU
factorisations of a run (PETSc's ``MatLUFactorNum`` count), the yielding share and punch
force at the end, and the largest difference of the final fields and the punch force from
Newton's at the same tolerance. A run of some meshes replaces only those meshes' records.

Run: ``python benchmarks/plastic_cost.py`` (serial; ``--h-window 0.02 0.01`` for about 10 min on
the 2-core VM beside other jobs); the dynamic case alone, one mesh a run (each under 5 min):
``python benchmarks/plastic_cost.py --cases dynamic --dynamic-h 0.006 --repeat 3``, then
``--dynamic-h 0.0045 --repeat 1``; recorded 2026-12-03: ``--dynamic-h 0.006 --repeat 2`` and
``--dynamic-h 0.0045 --dynamic-E 20e6 --dynamic-nu 0.25 --repeat 1 --dynamic-variants
plastic_elastic_qn elastic_explicit plastic_explicit plastic_fine_dt elastic_fine_dt``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
from machine import cpu_model, machine

from granfe.dynamics import GeneralizedAlpha
from granfe.explicit import CentralDifference
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
parser.add_argument("--cases", nargs="+", choices=("static", "dynamic"), default=["static", "dynamic"],
                    help="static: the load steps of the chamber; dynamic: the coupled chamber's time step")
parser.add_argument("--dynamic-h", type=float, nargs="+", default=[0.006] if SHORT else [0.006, 0.0045],
                    help="element sizes in the dynamic case's window [m] (one mesh each)")
parser.add_argument("--dynamic-steps", type=int, default=3 if SHORT else 6, help="time steps of the dynamic case")
parser.add_argument("--dynamic-E", type=float, nargs="+", default=[20e6, 1.2e6],
                    help="Young's moduli of the dynamic case [Pa], one set of runs each: 20 MPa puts the "
                         "P-wave 2.6 window elements a step (the affine constants' stiffness), 1.2 MPa "
                         "(with --dynamic-nu 0.36) is the window's stiffness probed in situ "
                         "(scenes/chamber_3d.toml: G 0.38-0.51 MPa, Poisson ratio 0.34-0.39)")
parser.add_argument("--dynamic-nu", type=float, nargs="+", default=[0.25, 0.36],
                    help="Poisson's ratios, one per --dynamic-E")
parser.add_argument("--dynamic-variants", nargs="+", default=None,
                    help="the dynamic variants to run (default all; elastic always)")
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

# ---- the dynamic step of the coupled 3D chamber -------------------------------------------
# scenes/chamber_3d.toml's box (24 cm wide, 8.4 cm deep) refined over a window 6 cm wide and
# 7 cm deep, its FE step (10 DEM steps of 14 us), the cone's speed; the soil at 100 kPa
# vertical (K0 0.44) and the Drucker-Prager cone of the README's 3D plastic run (30 deg,
# hardening 2 MPa, cohesionless); E such that the wave crosses 2.6 window elements a step
BOX = dict(width=0.24, depth=0.084, window_width=0.06, window_depth=0.07)
DT, SPEED, PUNCH = 1.4e-4, 1.0, 0.012        # [s], [m/s], radius of the pushed top nodes [m]
E_D, NU_D, RHO_D, LENGTH_D = 20e6, 0.25, 1600.0, 3e-3
S0 = (-44e3, -44e3, -100e3)                  # initial stress [Pa], tension positive
FINE = 8                                     # the fine-dt reference's steps per step


def dynamic_materials(E: float, nu: float):
    """The elastic and Drucker-Prager materials of the dynamic case (kappa = G / 2)."""
    G = E / (2 * (1 + nu))
    elastic = MicropolarMaterial(lam=E * nu / ((1 + nu) * (1 - 2 * nu)), mu=G - G / 4, kappa=G / 2,
                                 gamma=2 * G * LENGTH_D**2, rho=RHO_D, j=LENGTH_D**2)
    return elastic, DruckerPragerMaterial(elastic, 0.0, 30.0, 0.0, hardening=2e6,
                                          match="triaxial_compression", initial_stress=S0)


# name: plastic?, PETSc options, the stepper (GeneralizedAlpha's tangent, or "explicit":
# granfe.explicit.CentralDifference), Newton's absolute tolerance in units of the coupled run's,
# steps per step (the fine-dt references: their time-discretisation error is 1/64 of the others')
DYNAMIC = {"elastic": (False, {}, "elastic", 1.0, 1),
           "plastic_newton": (True, {}, "consistent", 1.0, 1),
           "plastic_newton_one_lu": (True, ONE_LU_PER_STEP, "consistent", 1.0, 1),
           "plastic_elastic_qn": (True, {}, "elastic", 1.0, 1),
           "plastic_newton_tight": (True, {}, "consistent", 1e-3, 1),
           "plastic_elastic_qn_tight": (True, {}, "elastic", 1e-3, 1),
           "elastic_explicit": (False, {}, "explicit", 1.0, 1),
           "plastic_explicit": (True, {}, "explicit", 1.0, 1),
           "elastic_fine_dt": (False, {}, "elastic", 1e-3, FINE),
           "plastic_fine_dt": (True, {}, "elastic", 1e-3, FINE)}


def dynamic_run(data, names, h: float, E: float, name: str, steps: int, tag: str) -> dict:
    """The box chamber pushed at the cone's speed on the top nodes within PUNCH of the axis for
    ``steps`` steps (generalized-alpha with rho_inf 0.8, as the coupled run, or explicit); per
    step the times and iterations (explicit: substeps), per run the LU factorisations, the
    punch force and the final field."""
    plastic, options, tangent, atol, split = DYNAMIC[name]
    elastic_m, plastic_m = dynamic_materials(E, NU_D)
    model, material = (MicropolarDruckerPrager, plastic_m) if plastic else (Micropolar, elastic_m)
    # the coupled chamber's solver and Newton tolerance (a millionth of the nodal force the
    # initial stress puts on a window element)
    problem = ContinuumProblem(data.mesh, model(material), facet_tags=data.facet_tags, tag_names=names,
                               degree=(1, 1), prefix=f"dyn_{tag}_", solver="redundant",
                               petsc_options={"snes_atol": atol * 1e-6 * abs(S0[2]) * h**2, **options})
    problem.fix("bottom", "u")
    problem.fix("bottom", "phi")
    for side, c in (("left", "u_x"), ("right", "u_x"), ("front", "u_y"), ("back", "u_y")):
        problem.fix(side, c)

    def punch(x):
        return np.isclose(x[2], 0.0) & (np.hypot(x[0], x[1]) <= PUNCH + 1e-9)

    problem.fix(punch, "u_x")
    problem.fix(punch, "u_y")
    settle = problem.fix(punch, "u_z", 0.0)
    dt = DT / split
    stepper = (CentralDifference(problem, dt) if tangent == "explicit"
               else GeneralizedAlpha(problem, dt, rho_inf=0.8, tangent=tangent))
    factorisations = PETSc.Log.Event("MatLUFactorNum")
    lu0 = factorisations.getPerfInfo()["count"]
    times, cpu, its = [], [], []
    for _ in range(steps * split):
        settle.value = -SPEED * (stepper.t + dt)
        comm.barrier()
        t0, c0 = time.perf_counter(), time.process_time()
        its.append(stepper.step())
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    yielding = problem.state.owned("yielding") if problem.state else np.zeros(0)
    share = comm.allreduce(float(yielding.sum()), MPI.SUM) / max(comm.allreduce(yielding.size, MPI.SUM), 1)
    return {"step_s": times, "step_cpu_s": cpu, "iterations": its, "path_s": float(sum(times)),
            "path_cpu_s": float(sum(cpu)), "punch_force": -problem.reaction(punch, "u_z"),
            "yielding_share": share, "fallbacks": stepper.fallbacks,
            "lu_factorisations": int(factorisations.getPerfInfo()["count"] - lu0),
            "dofs": problem.V.dofmap.index_map.size_global * problem.V.dofmap.index_map_bs,
            "w": problem.w.x.array[:problem.V.dofmap.index_map.size_local * problem.V.dofmap.index_map_bs].copy()}


def dynamic_case() -> dict:
    PETSc.Log.begin()
    out = {"what": "wall and CPU time of a dynamic (generalized-alpha) FE step of a 3D box chamber "
                   "shaped like the coupled 3D calibration chamber's, its top nodes about the axis "
                   "pushed at the cone's speed: micropolar Drucker-Prager by Newton on the consistent "
                   "tangent (plastic_newton, the step as it was), the same with one LU a step "
                   "(plastic_newton_one_lu), by quasi-Newton on the elastic Jacobian factorised once "
                   "(plastic_elastic_qn, GeneralizedAlpha's default now; _tight: Newton and it at a "
                   "thousandth of the absolute tolerance), against the elastic step "
                   "(one solve with the Jacobian factorised once, _AffineStep)",
           "inputs": {"box": BOX, "h_far": 0.03, "dt": DT, "speed": SPEED, "punch_radius": PUNCH,
                      "steps": args.dynamic_steps, "rho_inf": 0.8, "fine_dt_split": FINE,
                      "density": RHO_D, "length": LENGTH_D,
                      "kappa_over_G": 0.5, "friction_deg": 30.0, "dilatancy_deg": 0.0,
                      "cohesion": 0.0, "hardening": 2e6, "initial_stress": list(S0),
                      "solver": "redundant", "snes_atol": "1e-6 * 100 kPa * h_window^2 (the coupled run's)",
                      "ranks": comm.size, "short": SHORT},
           "meshes": []}
    variants = ["elastic", *[v for v in (args.dynamic_variants or DYNAMIC) if v != "elastic"]]
    for h in args.dynamic_h:
        data = build_chamber(comm, 3, shape="box", h_window=h, h_far=0.03, **BOX)
        names = {k: tag for k, (d, tag) in data.physical_groups.items() if d == 2}
        for E, nu in zip(args.dynamic_E, args.dynamic_nu, strict=True):
            out["meshes"].append(dynamic_mesh(data, names, h, E, nu, variants, warm=not out["meshes"]))
    return out


def dynamic_mesh(data, names, h: float, E: float, nu: float, variants: list[str], warm: bool) -> dict:
    """Every variant on one mesh and material, interleaved over the repeats."""
    before = machine()
    for name in variants if warm else ():                    # compile the forms (not timed)
        dynamic_run(data, names, h, E, name, 1, f"warm_{name}_{h:g}")
    runs: dict[str, list] = {}
    for rep in range(args.repeat):
        for name in variants:                                # interleaved: a busy spell hits all
            reps = 1 if DYNAMIC[name][4] > 1 else args.repeat    # a reference once
            if rep < reps:
                runs.setdefault(name, []).append(
                    dynamic_run(data, names, h, E, name, args.dynamic_steps, f"{name}{rep}_{h:g}_{E:g}"))
    entry = {"h_window": h, "E": E, "nu": nu, "dofs": runs["elastic"][-1]["dofs"],
             "cells": comm.allreduce(data.mesh.topology.index_map(3).size_local, MPI.SUM),
             "repeat": args.repeat, "machine": before, "commit": subprocess.run(
                 ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                 cwd=Path(__file__).parent).stdout.strip(),
             "load_average_1min_after": machine()["load_average_1min"]}

    def difference(rs, reference):
        """The largest difference of the fields at the end, relative to the largest value, and
        of the punch force, over the repeats."""
        pairs = list(zip(rs, reference, strict=False))
        return (max(comm.allreduce(float(np.abs(r["w"] - q["w"]).max()), MPI.MAX)
                    / comm.allreduce(float(np.abs(q["w"]).max()), MPI.MAX) for r, q in pairs),
                max(abs(r["punch_force"] / q["punch_force"] - 1) for r, q in zip(rs, reference, strict=False)))

    for name, rs in runs.items():
        e = summarise_dynamic(rs)
        plastic = DYNAMIC[name][0]
        if plastic and "plastic_newton" in runs:
            # the same answer as Newton's at the same tolerance (the implicit variants)
            reference = runs["plastic_newton_tight" if name.endswith("_tight") else "plastic_newton"]
            e["w_difference_vs_newton"], e["force_difference_vs_newton"] = difference(rs, reference)
        fine = runs.get("plastic_fine_dt" if plastic else "elastic_fine_dt")
        if fine and DYNAMIC[name][4] == 1:
            # the time-discretisation error: against the same model at an eighth of the step
            e["w_difference_vs_fine_dt"], e["force_difference_vs_fine_dt"] = difference(rs, fine * len(rs))
        if name != "elastic":
            for clock in ("s", "cpu_s"):
                e[f"step_{clock}_median_over_elastic"] = (e[f"step_{clock}_median"]
                                                          / runs_median(runs["elastic"], clock))
        entry[name] = e
    log(f"dynamic h {h:g}, E {E:g}: {entry['dofs']} dofs; elastic step "
        f"{1e3 * runs_median(runs['elastic'], 's'):.1f} ms")
    for name in runs:
        e = entry[name]
        log(f"  {name}: step median {e['step_s_median']:.3f} s (CPU {e['step_cpu_s_median']:.3f} s), "
            f"x {e.get('step_cpu_s_median_over_elastic', 1.0):.1f} the elastic step (CPU), iterations "
            f"{e['iterations'][:12]}, LU {e['lu_factorisations']}, yielding {100 * e['yielding_share']:.0f} %, "
            f"force {e['punch_force']:.9g} N, vs fine dt {e.get('force_difference_vs_fine_dt', float('nan')):.2e}")
    return entry


def runs_median(runs: list[dict], clock: str) -> float:
    return float(np.median(np.concatenate([r[f"step_{clock}"] for r in runs])))


def summarise_dynamic(runs: list[dict]) -> dict:
    out = {}
    for clock in ("s", "cpu_s"):        # wall and CPU (process) time, over all steps and repeats
        steps = np.concatenate([r[f"step_{clock}"] for r in runs])
        paths = np.array([r[f"path_{clock}"] for r in runs])
        out.update({f"step_{clock}_min": float(steps.min()), f"step_{clock}_median": float(np.median(steps)),
                    f"path_{clock}_min": float(paths.min()), f"path_{clock}_median": float(np.median(paths))})
    last = runs[-1]
    return {**out, "iterations": last["iterations"], "step_s_last_repeat": last["step_s"],
            "lu_factorisations": last["lu_factorisations"], "fallbacks": sum(r["fallbacks"] for r in runs),
            "yielding_share": last["yielding_share"], "punch_force": last["punch_force"]}


def static_case() -> dict:
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
    for entry in results["meshes"]:
        assert entry["plastic"]["yielding_share"] > 0.01, "the punch did not yield the soil"
        assert all(i == 1 for i in entry["elastic"]["newton_iterations"])
    return results


# ---- measure ---------------------------------------------------------------------------
# a file of earlier runs keeps the cases not run now
path = args.out / "results.json"
results = json.loads(path.read_text()) if path.exists() else {}
if "static" in args.cases:
    results.update(static_case())
if "dynamic" in args.cases:         # meshes measured now replace those of the same size
    new = dynamic_case()
    sizes = {(e["h_window"], e["E"]) for e in new["meshes"]}
    kept = [e for e in results.get("dynamic", {}).get("meshes", [])
            if (e["h_window"], e.get("E", E_D)) not in sizes]
    new["meshes"] = sorted(kept + new["meshes"], key=lambda e: (-e["h_window"], -e.get("E", E_D)))
    results["dynamic"] = new
if comm.rank == 0:
    args.out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(results, indent=1))
for entry in new["meshes"] if "dynamic" in args.cases else []:
    assert all(i == 1 for i in entry["elastic"]["iterations"])
    for name in ("plastic_newton", "plastic_explicit", "plastic_elastic_qn"):
        if name in entry:
            assert entry[name]["yielding_share"] > 0.01, "the punch did not yield the soil"
            assert entry[name]["fallbacks"] == 0
