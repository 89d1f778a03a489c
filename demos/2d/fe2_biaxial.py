"""Biaxial compression of a specimen whose material points are RVEs of disks (FE x DEM, seed 004).

This demo shows how to:

- consolidate a few periodic cells of disks to the confining pressure p0 (`dem.rve.RVE`),
  each on one rank (`coupling.fe2.consolidate_shared`), and give one to every quadrature
  point of a plane-strain mesh (`coupling.fe2.FE2`: one RVE a point, distributed with the
  cells over the ranks, moved between ranks after a load step to even their work),
- compress the specimen under a smooth platen with load stepping and cut-back, each load
  step a Newton on the RVE tangents kept as secants at every point (`coupling.fe2.MacroNewton`,
  ``tangent="secant"``), and log the residuals of every iteration,
- measure the localisation of the deformation: the deviatoric strain gained after the peak,
  per cell, against its mean (max / mean, the localisation index); at the default size (16
  points of 40 disks) the specimen hardens to a plateau (q/p 0.36 from ~0.8 % axial
  strain, dilating) and the strain is uneven from cell to cell, but no band of cells has
  formed by 1.5 % (measured: index 2.4 over the last 0.08 %; a larger mesh and strain are
  needed; the default run takes 6 minutes on 2 ranks),
- write the stress and the RVEs' coordination numbers as VTX, a checkpoint of every RVE,
  the stress-strain curve and the strain map to a PNG.

The specimen (width W, height 2 W) stands on a smooth base (held against sliding at its
bottom-left corner), is compressed by a smooth rigid platen (u_y prescribed, u_x free) and
carries p0 on both sides. Two dense packings (consolidated with a contact friction of 0.1,
then the grains' own) give the points, drawn at random; the first again, with a lower
contact friction, sits in the cells at the left edge, a third of the height up, and starts
the band. (A looser packing, consolidated with the grains' friction, coordination 2.95,
made a poor imperfection: its response to small strain changes is so rough that the
modified Newton cycled on it.) Disks of 2D RVEs have unit thickness: the springs are per
metre of thickness (kn / p0 = 1e3, overlaps ~1e-3 d).
Run: ``mpiexec -n 2 python demos/2d/fe2_biaxial.py`` (GRANFE_SHORT=1: 4 points, two steps).
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

from coupling.fe2 import FE2, FE2Writer, MacroNewton, consolidate_shared
from dem.rve import RVE, Grains, QuasiStatic
from granfe.models.quadrature_stress import QuadratureStress, QuadratureStressMaterial
from granfe.problem import ContinuumProblem
from granfe.stepping import LoadStepFailed, StepControl

SHORT = os.environ.get("GRANFE_SHORT") == "1"

# ---- parameters (SI) ------------------------------------------------------------------
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--width", type=float, default=0.05, help="specimen width W [m] (height 2 W)")
parser.add_argument("--nx", type=int, default=1 if SHORT else 2, help="quads across (2 triangles each)")
parser.add_argument("--p0", type=float, default=100e3, help="confining pressure [Pa]")
parser.add_argument("--disks", type=int, default=40, help="about this many disks an RVE")
parser.add_argument("--kn", type=float, default=1e8, help="normal spring [N/m per m thickness]")
parser.add_argument("--friction", type=float, default=0.5, help="contact friction coefficient")
parser.add_argument("--weak-friction", type=float, default=0.3,
                    help="contact friction of the weak cells' grains (the imperfection)")
parser.add_argument("--strain", type=float, default=1e-3 if SHORT else 0.015,
                    help="final axial strain (compression)")
parser.add_argument("--step", type=float, default=5e-4,
                    help="first (and largest) axial strain step")
parser.add_argument("--tangent", default="secant", help="MacroNewton.tangent")
parser.add_argument("--tangent-every", type=int, default=1000,
                    help="MacroNewton.tangent_every (secant: perturbation tangents this often)")
parser.add_argument("--seed", type=int, default=1)
parser.add_argument("--out", type=Path, default=Path("output/fe2_biaxial"))
args = parser.parse_args()

comm = MPI.COMM_WORLD
W, HEIGHT, P0 = args.width, 2 * args.width, args.p0
NX, NY = args.nx, 2 * args.nx
# max_steps: a relaxation that has not converged by then is taken as failed and the load step
# cut back. The longest that converged over the full run was 27900 steps (mean ~600); a
# failed one costs max_steps on one rank while the others wait (at the default 200000, 40 s
# a failure: most of a 2-rank run's wall). The run is the same to the last digit with either
# (the 16 failures fail at both).
SOLVER = QuasiStatic(force_tol=1e-3, stress_tol=2e-3, ramp_steps=200, strain_rate=2e-6,
                     max_steps=30_000)
NEWTON = MacroNewton(force_tol=1e-3, max_it=25, tangent=args.tangent,
                     tangent_every=args.tangent_every)
CONTROL = StepControl(first=args.step, min_step=args.step / 16, max_step=args.step)


def log(msg):
    if comm.rank == 0:
        print(msg, flush=True)


if comm.rank == 0:
    args.out.mkdir(parents=True, exist_ok=True)
t_start = time.perf_counter()

# ---- RVEs: each packing consolidated on one rank, its state sent to the others -------------
grains = dict(n=args.disks, dim=2, kn=args.kn, kt=0.7 * args.kn, friction=args.friction)
n_dense = 1 if SHORT else 2
makers = [lambda s=s: RVE.consolidate(Grains(**grains, seed=args.seed + s,
                                             consolidation_friction=0.1), P0, SOLVER)
          for s in range(n_dense)]
makers.append(lambda: RVE.consolidate(Grains(**{**grains, "friction": args.weak_friction},
                                             seed=args.seed, consolidation_friction=0.1),
                                      P0, SOLVER))
prototypes = consolidate_shared(comm, makers)
dense = prototypes[:n_dense]
t_rves = time.perf_counter() - t_start
log(f"RVEs consolidated in {t_rves:.1f} s: coordination "
    + ", ".join(f"{r.coordination():.2f}" for r in prototypes) + ", solid fraction "
    + ", ".join(f"{r.solid_fraction():.3f}" for r in prototypes))

# ---- macro problem ------------------------------------------------------------------------
domain = mesh.create_rectangle(comm, [[0, 0], [W, HEIGHT]], [NX, NY], mesh.CellType.triangle)
problem = ContinuumProblem(domain, QuadratureStress(QuadratureStressMaterial()),
                           quadrature_degree=1, solver="redundant", prefix="fe2_biaxial_")
problem.fix(lambda x: np.isclose(x[1], 0.0), "u_y")
problem.fix_point((0.0, 0.0), "u_x")
platen = problem.fix(lambda x: np.isclose(x[1], HEIGHT), "u_y", 0.0)
problem.traction(lambda x: np.isclose(x[0], 0.0), (P0, 0.0))
problem.traction(lambda x: np.isclose(x[0], W), (-P0, 0.0))

# the weak cells: the input cells at the left edge, a third of the height up
weak_row = NY // 3
rng = np.random.default_rng(args.seed)
draw = rng.integers(0, len(dense), size=2 * NX * NY)


def pick(g: int) -> int:
    quad = g // 2  # create_rectangle: two triangles a quad, quads row by row
    return len(dense) if (quad % NX == 0 and quad // NX == weak_row) else int(draw[g])


fe2 = FE2(problem, prototypes, pick=pick, settings=NEWTON, log=log)
n_points = comm.allreduce(fe2.n, MPI.SUM)
log(f"{n_points} RVEs on {comm.size} rank(s) ({fe2.n} here)")
writer = FE2Writer(fe2, args.out)
writer.write(0.0)

# ---- load path -------------------------------------------------------------------------
curve = [dict(axial_strain=0.0, q_over_p=0.0, volumetric_strain=0.0, sigma_yy=-P0)]
strains = [fe2.strain()]


def apply(t):
    platen.value = -t * HEIGHT


def on_step(t, its):
    sig_yy = problem.reaction(lambda x: np.isclose(x[1], HEIGHT), "u_y") / W
    e = fe2.strain()
    vol = comm.allreduce(float(e[:, :2].sum()), MPI.SUM) / n_points
    p = 0.5 * (P0 - sig_yy)
    curve.append(dict(axial_strain=t, q_over_p=(-sig_yy - P0) / (2 * p), volumetric_strain=vol,
                      sigma_yy=sig_yy, iterations=its))
    strains.append(e)
    writer.write(t)
    log(f"  axial strain {t:.4f}: sigma_yy {sig_yy / 1e3:.1f} kPa, q/p "
        f"{curve[-1]['q_over_p']:.3f}, volumetric strain {vol:.2e}")


status = "finished"
try:
    fe2.follow(apply, args.strain, CONTROL, on_step=on_step)
except LoadStepFailed as err:
    status = f"stopped: {err}"
    log(status)
fe2.write_checkpoint(args.out / "checkpoint")
writer.close()
wall = time.perf_counter() - t_start

# ---- localisation: deviatoric strain gained after the peak, per point -----------------
q = np.array([c["q_over_p"] for c in curve])
k_peak = int(np.argmax(q))


def deviatoric(e):
    """Equivalent deviatoric strain sqrt(2/3 e':e') of Mandel plane strain (ezz = 0)."""
    m = (e[:, 0] + e[:, 1]) / 3
    return np.sqrt(2 / 3 * ((e[:, 0] - m) ** 2 + (e[:, 1] - m) ** 2 + m**2 + e[:, 2] ** 2))


gained = deviatoric(strains[-1] - strains[k_peak])
gained_all = fe2.gather(gained)
deviatoric_all = fe2.gather(deviatoric(strains[-1]))
geometry = domain.geometry.x[domain.geometry.dofmaps[0][fe2.point_cell], :2]
xy_all = fe2.gather(geometry.reshape(fe2.n, -1))
coord_all = fe2.gather(fe2.per_point(RVE.coordination))
stats = {k: comm.allreduce(v, MPI.SUM) for k, v in fe2.stats.items()}
per_rank = comm.gather(dict(fe2.stats, points=fe2.n, rves_held=len(fe2.held),
                            cpu_seconds=time.process_time()), root=0)
iterations = [c.get("iterations") for c in curve[1:]]
rates = [float(np.exp(np.mean(np.diff(np.log(np.asarray(h)[1:]))))) for h in fe2.history
         if len(h) > 2]

if comm.rank == 0:
    index = float(gained_all.max() / gained_all.mean()) if gained_all.mean() > 0 else None
    results = dict(
        inputs=dict(vars(args), out=str(args.out), short=SHORT, solver=SOLVER.__dict__,
                    newton=NEWTON.__dict__, ranks=comm.size),
        status=status, points=n_points, wall_seconds=wall, rve_consolidation_seconds=t_rves,
        curve=curve, peak=dict(index=k_peak, q_over_p=float(q[k_peak]),
                               axial_strain=curve[k_peak]["axial_strain"]),
        localisation_index=index, newton_iterations=iterations,
        deviatoric_strain_final=deviatoric_all.tolist(),
        newton_contraction_mean=float(np.mean(rates)) if rates else None,
        residual_histories=fe2.history, rve_stats=stats, per_rank=per_rank,
        steps=[dict(seconds=r["seconds"], iterations=r["iterations"], rves_moved=r["rves_moved"])
               for r in fe2.log_rows],
        rve_steps_per_second=stats["rve_steps"] / max(stats["rve_seconds"], 1e-300) * comm.size,
        coordination_final=dict(min=float(coord_all.min()), max=float(coord_all.max())))
    (args.out / "results.json").write_text(json.dumps(results, indent=1, default=float))
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    fig, ax = plt.subplots(1, 3, figsize=(13, 5), width_ratios=[1.3, 1, 1])
    a = np.array([c["axial_strain"] for c in curve])
    ax[0].plot(100 * a, q, "o-", label="q / p")
    ax[0].set_xlabel("axial strain [%]")
    ax[0].set_ylabel("q / p  (q = (sigma_1 - sigma_3) / 2)")
    ax0 = ax[0].twinx()
    ax0.plot(100 * a, [100 * c["volumetric_strain"] for c in curve], "s--", color="C1")
    ax0.set_ylabel("volumetric strain [%] (extension +)", color="C1")
    ax[0].axvline(100 * a[k_peak], color="grey", lw=0.5)
    ax[0].set_title(f"{n_points} RVEs of ~{args.disks} disks")
    for axis, values, title in ((ax[1], gained_all, "deviatoric strain after the peak"),
                                (ax[2], coord_all, "coordination number")):
        pc = PolyCollection(xy_all.reshape(-1, 3, 2), array=values, cmap="viridis",
                            edgecolors="k", linewidths=0.2)
        axis.add_collection(pc)
        axis.set_xlim(0, W)
        axis.set_ylim(0, HEIGHT)
        axis.set_aspect("equal")
        axis.set_title(title)
        fig.colorbar(pc, ax=axis, shrink=0.8)
    fig.tight_layout()
    fig.savefig(args.out / "fe2_biaxial.png", dpi=120)
    log(f"peak q/p {q[k_peak]:.3f} at {100 * a[k_peak]:.2f} %; localisation index "
        f"{index}; {wall:.0f} s; results in {args.out}")

    # ---- checks --------------------------------------------------------------------------
    assert status == "finished", status
    assert all(its is not None and its <= NEWTON.max_it for its in iterations)
    assert 0.05 < q[k_peak] < 0.9, "mobilised friction outside the range of frictional disks"
    if not SHORT:
        assert k_peak < len(q) - 1, "no peak: the specimen still hardens at the end"
        assert index is not None and index > 2.0, "no localisation: the strain after the peak is spread evenly"
