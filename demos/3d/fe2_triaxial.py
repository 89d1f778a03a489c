"""Triaxial compression of a specimen whose material points are RVEs of spheres (FE x DEM, 3D).

This demo shows how to:

- consolidate a periodic cell of spheres to the confining pressure p0 (`dem.rve.RVE`) and
  give a clone of it to every quadrature point of a tetrahedral mesh (`coupling.fe2.FE2`:
  one point a tetrahedron, the RVEs distributed over the ranks and evened by their work),
- compress the specimen at constant confining pressure under a smooth platen, with load
  stepping and cut-back, each load step a Newton on the points' secant tangents
  (`coupling.fe2.MacroNewton`, ``tangent="secant"``),
- check it against the single RVE driven directly under the same mixed control (sigma_xx =
  sigma_yy = -p0, no shear stress, eps_zz prescribed): every point is a clone of that RVE
  and the specimen deforms homogeneously, so the two answers must agree to the tolerances
  of the relaxations (the paths inside a step differ: the macro Newton sends each point a
  straight strain increment, the direct run servos its stresses along the way),
- write the stress-strain curves to a results json and a PNG.

The specimen is a cube of side L (n^3 hexahedra of six tetrahedra each): rollers on the
planes x = 0, y = 0 and z = 0 (symmetry), p0 on x = L and y = L, the top z = L moved down.
The grains are seed 004's (0.03-0.07 mm, kn / kt = 100 / 70 kN/m, tan 15 deg friction),
consolidated with a contact friction of 0.1 (denser), then their own.

Run: ``mpiexec -n 2 python demos/3d/fe2_triaxial.py`` (GRANFE_SHORT=1: one step).
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
from dolfinx import mesh

from coupling.fe2 import FE2, MacroNewton, consolidate_shared
from dem.rve import RVE, Grains, QuasiStatic, to_mandel
from granfe.models.quadrature_stress import QuadratureStress, QuadratureStressMaterial
from granfe.problem import ContinuumProblem
from granfe.stepping import LoadStepFailed, StepControl

SHORT = os.environ.get("GRANFE_SHORT") == "1"

# ---- parameters (SI) ------------------------------------------------------------------
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--side", type=float, default=0.01, help="specimen side L [m]")
parser.add_argument("--n", type=int, default=1, help="hexahedra along a side (6 tetrahedra each)")
parser.add_argument("--p0", type=float, default=100e3, help="confining pressure [Pa]")
parser.add_argument("--spheres", type=int, default=40, help="about this many spheres an RVE")
parser.add_argument("--strain", type=float, default=2.5e-4 if SHORT else 1e-3,
                    help="final axial strain (compression)")
parser.add_argument("--step", type=float, default=2.5e-4,
                    help="largest axial strain step (the first is a tenth)")
parser.add_argument("--seed", type=int, default=1)
parser.add_argument("--out", type=Path, default=Path("output/fe2_triaxial"))
args = parser.parse_args()

comm = MPI.COMM_WORLD
L, P0 = args.side, args.p0
GRAINS = Grains(n=args.spheres, dim=3, seed=args.seed, consolidation_friction=0.1)
# Past ~0.1 % axial strain (q/p ~0.6-0.7) some cells of 40 spheres no longer come to rest,
# whatever the strain step: at force_tol 1e-3 / max_steps 3e4 the load stepping stopped at
# 0.14 % (steps cut to 1.6e-5), at 2e-3 / 1e5 at 0.16 %. Hence the default final strain.
SOLVER = QuasiStatic(force_tol=1e-3, stress_tol=2e-3, ramp_steps=200, strain_rate=2e-6,
                     max_steps=30_000)
ROUGH = replace(SOLVER, force_tol=1e-2, stress_tol=1e-2)
NEWTON = MacroNewton(force_tol=1e-3, max_it=25, tangent="secant", tangent_every=1000)
# from a tenth of the step, doubled after every converged step (the grains are stiff: the
# rise to the plateau is within the first 1e-4)
CONTROL = StepControl(first=args.step / 10, min_step=args.step / 16, max_step=args.step, grow=2.0,
                      easy=NEWTON.max_it)
Q_TOL = 0.1  # |q/p specimen - q/p RVE| at every step: the relaxations' tolerances and paths


def log(msg):
    if comm.rank == 0:
        print(msg, flush=True)


if comm.rank == 0:
    args.out.mkdir(parents=True, exist_ok=True)
t_start = time.perf_counter()

# ---- the RVE: consolidated on one rank, its state sent to the others ------------------------
def consolidated() -> RVE:
    """GRAINS at p0, relaxed to ROUGH (the isotropic state of a cell of ~60 spheres creeps
    for ~10^5 steps before all six stresses sit within 2e-3 p0 of p0), then loaded with
    SOLVER's tolerances."""
    rve = RVE.consolidate(GRAINS, P0, ROUGH)
    rve.solver = SOLVER
    return rve


(proto,) = consolidate_shared(comm, [consolidated])
t_rve = time.perf_counter() - t_start
log(f"RVE of {proto.sim.p.n} spheres consolidated in {t_rve:.1f} s: coordination "
    f"{proto.coordination():.2f}, solid fraction {proto.solid_fraction():.3f}")

# ---- macro problem ------------------------------------------------------------------------
domain = mesh.create_box(comm, [[0, 0, 0], [L, L, L]], [args.n] * 3, mesh.CellType.tetrahedron)
problem = ContinuumProblem(domain, QuadratureStress(QuadratureStressMaterial()),
                           quadrature_degree=1, solver="redundant", prefix="fe2_triaxial_")
for axis in range(3):
    problem.fix(lambda x, a=axis: np.isclose(x[a], 0.0), "u_" + "xyz"[axis])
platen = problem.fix(lambda x: np.isclose(x[2], L), "u_z", 0.0)
problem.traction(lambda x: np.isclose(x[0], L), (-P0, 0.0, 0.0))
problem.traction(lambda x: np.isclose(x[1], L), (0.0, -P0, 0.0))
fe2 = FE2(problem, [proto], settings=NEWTON, log=log)
n_points = comm.allreduce(fe2.n, MPI.SUM)
log(f"{n_points} RVEs on {comm.size} rank(s) ({fe2.n} here)")


def mean_stress(fe2):
    """Mean committed Mandel stress over every point (the tetrahedra have equal volumes)."""
    return comm.allreduce(fe2.stress().sum(axis=0), MPI.SUM) / n_points


# ---- load path -------------------------------------------------------------------------
curve = [dict(axial_strain=0.0, q_over_p=0.0, volumetric_strain=0.0, sigma_zz=-P0)]


def apply(t):
    platen.value = -t * L


def on_step(t, its):
    sig_zz = problem.reaction(lambda x: np.isclose(x[2], L), "u_z") / L**2
    s = mean_stress(fe2)
    vol = comm.allreduce(float(fe2.strain()[:, :3].sum()), MPI.SUM) / n_points
    p = -(s[0] + s[1] + sig_zz) / 3
    curve.append(dict(axial_strain=t, q_over_p=(-sig_zz + 0.5 * (s[0] + s[1])) / p,
                      volumetric_strain=vol, sigma_zz=sig_zz, lateral=[s[0], s[1]],
                      iterations=its, seconds=fe2.log_rows[-1]["seconds"]))
    log(f"  axial strain {t:.4f}: sigma_zz {sig_zz / 1e3:.1f} kPa, q/p "
        f"{curve[-1]['q_over_p']:.3f}, volumetric strain {vol:.2e}")


status = "finished"
t_steps = time.perf_counter()
try:
    fe2.follow(apply, args.strain, CONTROL, on_step=on_step)
except LoadStepFailed as err:
    status = f"stopped: {err}"
    log(status)
t_steps = time.perf_counter() - t_steps

# ---- the RVE driven directly along the specimen's axial strains -----------------------------
t_direct = time.perf_counter()
direct = []
if comm.rank == 0:
    rve = RVE(proto.sim, proto.solver)
    proto.restore()
    mask = ~np.eye(3, dtype=bool)
    mask[0, 0] = mask[1, 1] = True  # all but eps_zz as stress
    last = 0.0
    for c in curve[1:]:
        de = np.zeros((3, 3))
        de[2, 2] = -(c["axial_strain"] - last)
        last = c["axial_strain"]
        sig = rve.load(strain_increment=de, stress=-P0 * np.eye(3), mask=mask)["stress"]
        p = -np.trace(sig) / 3
        direct.append(dict(axial_strain=last, q_over_p=(-sig[2, 2] + 0.5 * (sig[0, 0] + sig[1, 1]))
                           / p, volumetric_strain=float(np.trace(rve.strain()))))
    proto.restore()
t_direct = time.perf_counter() - t_direct
wall = time.perf_counter() - t_start
stats = {k: comm.allreduce(v, MPI.SUM) for k, v in fe2.stats.items()}
per_rank = comm.gather(dict(fe2.stats, points=fe2.n, rves_held=len(fe2.held)), root=0)
coordination = fe2.gather(fe2.per_point(RVE.coordination))

if comm.rank == 0:
    q = np.array([c["q_over_p"] for c in curve])
    q_direct = np.array([0.0] + [d["q_over_p"] for d in direct])
    gap = float(np.abs(q - q_direct).max())
    results = dict(
        inputs=dict(vars(args), out=str(args.out), short=SHORT, grains=GRAINS.__dict__,
                    solver=SOLVER.__dict__, newton=NEWTON.__dict__, ranks=comm.size),
        status=status, points=n_points, spheres=int(proto.sim.p.n),
        wall_seconds=wall, rve_consolidation_seconds=t_rve, load_steps_seconds=t_steps,
        direct_rve_seconds=t_direct, curve=curve, direct=direct,
        q_over_p_gap_max=gap, q_tol=Q_TOL, rve_stats=stats, per_rank=per_rank,
        residual_histories=fe2.history, coordination_final=coordination.tolist(),
        initial=dict(coordination=proto.coordination(), solid_fraction=proto.solid_fraction(),
                     stress=to_mandel(proto.stress()).tolist()))
    (args.out / "results.json").write_text(json.dumps(results, indent=1, default=float))
    import matplotlib.pyplot as plt

    a = 100 * np.array([c["axial_strain"] for c in curve])
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.5))
    ax[0].plot(a, q, "o-", label=f"specimen: {n_points} RVEs (FE x DEM)")
    ax[0].plot(a, q_direct, "s--", label="one RVE driven directly")
    ax[0].set_xlabel("axial strain [%]")
    ax[0].set_ylabel("q / p")
    ax[0].set_title(f"triaxial at p0 = {P0 / 1e3:.0f} kPa, {proto.sim.p.n} spheres an RVE\n"
                    "q = -sigma_zz + (sigma_xx + sigma_yy) / 2", fontsize=10)
    ax[0].legend()
    ax[1].plot(a, [100 * c["volumetric_strain"] for c in curve], "o-", label="specimen")
    ax[1].plot(a, [0.0] + [100 * d["volumetric_strain"] for d in direct], "s--",
               label="one RVE")
    ax[1].set_xlabel("axial strain [%]")
    ax[1].set_ylabel("volumetric strain [%] (extension +)")
    ax[1].legend()
    fig.tight_layout()
    fig.savefig(args.out / "fe2_triaxial.png", dpi=120)
    log(f"q/p {q[-1]:.3f} at {a[-1]:.2f} % (one RVE: {q_direct[-1]:.3f}; largest gap "
        f"{gap:.3f}); {wall:.0f} s ({t_steps:.0f} s of load steps); results in {args.out}")

    # ---- checks --------------------------------------------------------------------------
    assert status == "finished", status
    assert all(c["iterations"] <= NEWTON.max_it for c in curve[1:])
    assert gap <= Q_TOL, f"the specimen left the single RVE's path by {gap:.3f} in q/p"
    if not SHORT:
        assert 0.2 < q.max() < 1.5, "mobilised friction outside the range of frictional spheres"
        assert math.isfinite(curve[-1]["volumetric_strain"])
