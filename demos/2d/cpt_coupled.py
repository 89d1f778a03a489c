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
import os
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np

from coupling.apps.penetration.coupled import PenetrationParameters
from coupling.apps.penetration.run import run_penetration

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

# ---- set-up, run and outputs (settle, mesh, couple, push; see coupling.apps.penetration.coupled) -----------
results = run_penetration(prm, args.out, comm, frames=args.frames, progress=False, log=log)
history = results["history"]
for h in history[:: max(1, len(history) // args.frames)]:
    log(f"  depth {h['depth'] * 1e3:5.1f} mm: q_c = {h['q_c'] / 1e3:7.2f} kPa, "
        f"f_s = {h['f_s'] / 1e3:6.2f} kPa")

# ---- checks -------------------------------------------------------------------------------------------
assert all(np.isfinite(h["q_c"]) for h in history)
assert max(h["q_c"] for h in history) > 0, "the cone never met the grains"
