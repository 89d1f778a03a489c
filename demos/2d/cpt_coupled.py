"""Coupled cone penetration (2D): frictional grains around the cone, micropolar continuum
everywhere else.

This demo shows how to:

- settle a DE window of frictional disks under gravity inside a ghost band,
- derive the continuum's micropolar constants and density from the settled packing,
- push a rigid 60 degree cone (a clump of ghost disks) at constant velocity while the DE
  window is coupled to the gmsh-meshed FE chamber (ghosts follow the FE displacement,
  window FE nodes follow the grains by the L2 projection, relaxed),
- record the tip resistance q_c and the sleeve friction f_s against depth, and write the
  grains (VTU/PVD), the continuum (VTX) and pictures.

Run: ``mpiexec -n 2 python demos/2d/cpt_coupled.py [--depth 0.04 --velocity 0.2]``.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401

import numpy as np
from mpi4py import MPI

from coupling.penetration import CoupledPenetration, PenetrationParameters
from dem.io import ParticleWriter
from granfe.io import ContinuumWriter, render_png

SHORT = os.environ.get("GRANFE_SHORT") == "1"

# ---- parameters (SI, per unit thickness) ------------------------------------------------------
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--depth", type=float, default=0.01 if SHORT else 0.04, help="penetration depth [m]")
parser.add_argument("--velocity", type=float, default=0.2, help="cone velocity [m/s]")
parser.add_argument("--cone-radius", type=float, default=0.01, help="cone radius [m]")
parser.add_argument("--radius", type=float, default=1.5e-3, help="grain radius [m]")
parser.add_argument("--friction", type=float, default=0.5)
parser.add_argument("--kn", type=float, default=2.0e5, help="contact stiffness [N/m per m]")
parser.add_argument("--relaxation", type=float, default=0.3)
parser.add_argument("--frames", type=int, default=5, help="output frames")
parser.add_argument("--out", type=Path, default=Path("output/cpt_coupled"))
args = parser.parse_args()
comm = MPI.COMM_WORLD


def log(msg):
    if comm.rank == 0:
        print(msg, flush=True)


prm = PenetrationParameters(depth=args.depth, velocity=args.velocity, cone_radius=args.cone_radius,
                            radius=args.radius, friction=args.friction, kn=args.kn,
                            relaxation=args.relaxation)

# ---- set-up: settle, mesh, couple -----------------------------------------------------------------
t0 = time.perf_counter()
cpt = CoupledPenetration(prm, comm, log=log)
log(f"set-up {time.perf_counter() - t0:.1f} s: {cpt.n_grains} grains, coordination "
    f"{cpt.contact_stats['coordination']:.2f}, continuum lam = mu = {cpt.material_fe.lam:.3g} Pa, "
    f"kappa = {cpt.material_fe.kappa:.3g} Pa, rho = {cpt.material_fe.rho:.0f} kg/m^3")

# ---- run with outputs --------------------------------------------------------------------------------
if comm.rank == 0:
    args.out.mkdir(parents=True, exist_ok=True)
comm.barrier()
grains = ParticleWriter(args.out, "grains") if comm.rank == 0 else None
fields = ContinuumWriter(cpt.problem, args.out, name="continuum")
n_steps = int(np.ceil(prm.depth / prm.velocity / cpt.dt_fe))
every = max(1, n_steps // args.frames)


def frame(h):
    if h["step"] % every and h["step"] != n_steps:
        return
    log(f"  depth {h['depth'] * 1e3:5.1f} mm: q_c = {h['q_c'] / 1e3:7.2f} kPa, "
        f"f_s = {h['f_s'] / 1e3:6.2f} kPa, ghost mismatch {h['interface_mismatch']:.2f}")
    fields.write(h["time"])
    if grains is not None:
        p = cpt.sim.p
        grains.write(h["time"], p.x, p.radius, velocity=p.v, kind=p.kind.astype(float),
                     force=p.force)


t0 = time.perf_counter()
history = cpt.run(progress=frame)
t_run = time.perf_counter() - t0
fields.close()
if grains is not None:
    grains.close()

# ---- results and figures -------------------------------------------------------------------------
p = cpt.sim.p


def overlay(plotter, warp):
    import pyvista

    cloud = pyvista.PolyData(p.x.copy())
    cloud["kind"] = p.kind.astype(float)
    plotter.add_mesh(cloud, scalars="kind", cmap=["white", "red"], point_size=3,
                     render_points_as_spheres=True, show_scalar_bar=False)


W = 0.5 * prm.chamber_width
render_png(cpt.problem, args.out / "cpt.png", "u_magnitude", warp=0, overlay=overlay,
           box=(-W / 2, W / 2, cpt.surface - 0.12, cpt.surface + 0.03),
           title=f"|u| of the continuum; grains (red: ghosts, cone) at depth {prm.depth * 100:.1f} cm")
if comm.rank == 0:
    import matplotlib.pyplot as plt

    depth = np.array([h["depth"] for h in history])
    qc = np.array([h["q_c"] for h in history])
    fs = np.array([h["f_s"] for h in history])
    fig, axes = plt.subplots(1, 2, figsize=(8, 5), sharey=True)
    axes[0].plot(qc / 1e3, depth * 100)
    axes[0].set_xlabel("tip resistance q_c [kPa]")
    axes[0].set_ylabel("depth [cm]")
    axes[0].invert_yaxis()
    axes[1].plot(fs / 1e3, depth * 100)
    axes[1].set_xlabel("sleeve friction f_s [kPa]")
    fig.tight_layout()
    fig.savefig(args.out / "tip_resistance.png", dpi=120)
    with open(args.out / "tip_resistance.csv", "w", newline="") as f:
        wr = csv.DictWriter(f, fieldnames=list(history[0]))
        wr.writeheader()
        wr.writerows(history)
    results = {"inputs": vars(args) | {"out": str(args.out), "short": SHORT, "ranks": comm.size},
               "parameters": prm.__dict__, "grains": cpt.n_grains,
               "continuum": {"lam": cpt.material_fe.lam, "mu": cpt.material_fe.mu,
                             "kappa": cpt.material_fe.kappa, "rho": cpt.material_fe.rho,
                             "dofs": cpt.problem.V.dofmap.index_map.size_global},
               "packing": cpt.contact_stats, "dem_dt": cpt.sim.dt, "fe_dt": cpt.dt_fe,
               "run_time_s": t_run, "history": history,
               "q_c_mean_last_half": float(qc[len(qc) // 2:].mean())}
    (args.out / "results.json").write_text(json.dumps(results, indent=2, default=float))
    log(f"{len(history)} FE steps, {cpt.sim.nsteps} DEM steps in {t_run:.1f} s; outputs in {args.out}")

# ---- checks -------------------------------------------------------------------------------------------
assert all(np.isfinite(h["q_c"]) for h in history)
assert max(h["q_c"] for h in history) > 0, "the cone never met the grains"
