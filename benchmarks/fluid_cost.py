"""Cost of the Darcy pore fluid in a DEM step against the dry step, at the same grain count.

A 3D box of spheres on a simple-cubic lattice (touching, a small random velocity, gravity,
walls: a quiet packing that needs no settling) is stepped dry and with a
`coupling.pore_fluid.DarcyFlow` (P1 porosity on tetrahedra, ~80 grains a node's support:
affine cells, which `coupling.locate` pulls back in one vectorised solve), drained top, a
fluid step every ``--every`` DEM steps with the implicit drag in every DEM step (inside the
fused step loop: ``sim.step(m, drag=...)``). Measured in ``--repeat`` interleaved rounds
(each round times the dry run, the drag alone and every wet case once, fresh simulations,
kernels and forms compiled by a warm-up first, so a change of the machine's load falls on
all cases alike): the wall and CPU time per DEM step; the fluid's share, wet / dry - 1,
from the medians and from the minima; the drag alone (the fluid solved once, then only the
drag); and where a fluid step's CPU time goes (grains to mesh: locating the grains and the
basis at their centroids, porosity and velocity; the pressure's assembly and solve; the
forces back: seepage, drag coefficients, the DEM's external forces and the drag's set-up).
The CPU model and the load from ``benchmarks/machine.py``.

Run: ``python benchmarks/fluid_cost.py`` (serial; ~30 s on the 2-core VM);
``GRANFE_SHORT=1`` for a quick look.
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
from machine import machine

from coupling.pore_fluid import DarcyFlow, PoreFluidParameters
from dem import ContactMaterial, Particles, Simulation, box_walls
from dem.packing import lattice_packing

SHORT = os.environ.get("GRANFE_SHORT") == "1"
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--n-side", type=int, nargs="+", default=[8] if SHORT else [8, 13],
                    help="grains per box side (n^3 grains)")
parser.add_argument("--every", type=int, nargs="+", default=[10, 50] if SHORT else [10, 50, 100],
                    help="DEM steps per fluid step")
parser.add_argument("--steps", type=int, default=200 if SHORT else 600, help="DEM steps timed")
parser.add_argument("--repeat", type=int, default=2 if SHORT else 3)
parser.add_argument("--out", type=Path, default=Path("output/fluid_cost"))
args = parser.parse_args()
R = 1e-3
MAT = ContactMaterial(E=1e8, nu=0.25, density=2650.0, friction=0.5, restitution=0.3,
                      law="linear", kn=2e4, kt=1e4)




def box(n):
    """A fresh simulation of n^3 touching spheres in a box (and the box's size [m])."""
    side = 2 * R * n
    x, r = lattice_packing([0, 0, 0], [side] * 3, R, kind="sc")
    v = np.random.default_rng(0).normal(0, 1e-3, (len(r), 3))
    p = Particles.spheres(x, r, MAT.density, dim=3, v=v)
    sim = Simulation(p, MAT, walls=box_walls([0, 0, 0], [side] * 3, top=True),
                     gravity=(0, 0, -9.81), safety=0.2)
    return sim, side


def fluid_on(sim, side, n):
    cells = max(1, round(n / 4))     # 6 tetrahedra a cube: ~10 grains each, ~80 a P1 node
    # offset from the lattice, whose sites would lie on the cells' faces and diagonals (a
    # grain there changes cell at every rattle and is searched for anew)
    lo, hi = -R * np.array([0.31, 0.17, 0.23]), side + R * np.array([0.29, 0.41, 0.37])
    msh = mesh.create_box(MPI.COMM_SELF, [lo, hi], [cells] * 3, mesh.CellType.tetrahedron)
    fl = DarcyFlow(msh, sim, PoreFluidParameters(porosity_max=0.9, porosity_space="P1"))
    fl.drained(lambda X: np.isclose(X[2], hi[2]))
    return fl


def timed(run, steps):
    """(wall, CPU) seconds per DEM step of ``run()``."""
    t, c = time.perf_counter(), time.process_time()
    run()
    return (time.perf_counter() - t) / steps, (time.process_time() - c) / steps


def time_dry(n, steps):
    sim, _ = box(n)
    return timed(lambda: sim.step(steps), steps)


def time_wet(n, steps, every):
    sim, side = box(n)
    fl = fluid_on(sim, side, n)
    fl.advance(every, every)            # forms compiled, solver set up
    return timed(lambda: fl.advance(steps, every), steps)


def time_drag(n, steps):
    sim, side = box(n)
    fl = fluid_on(sim, side, n)
    fl.step(steps * sim.dt)
    return timed(lambda: sim.step(steps, drag=fl.drag), steps)


def fluid_step_parts(n, every, blocks=30):
    """CPU seconds of one fluid step and of its parts, mean over ``blocks`` fluid steps
    with ``every`` DEM steps between (the grains move, as in a run)."""
    sim, side = box(n)
    fl = fluid_on(sim, side, n)
    fl.advance(every, every)
    parts = {"grains_to_mesh": 0.0, "pressure_solve": 0.0, "forces_to_grains": 0.0}
    for _ in range(blocks):
        c0 = time.process_time()
        fl.update_from_grains()
        c1 = time.process_time()
        fl._problem.solve()      # what DarcyFlow.solve adds to these is bookkeeping
        c2 = time.process_time()
        fl.apply_forces()
        c3 = time.process_time()
        for k, dc in zip(parts, (c1 - c0, c2 - c1, c3 - c2), strict=True):
            parts[k] += dc / blocks
        sim.step(every, drag=fl.drag)
    parts["total"] = sum(parts.values())
    return parts


def stats(samples, k):
    """min and median of the k-th member (0 wall, 1 CPU) of (wall, CPU) samples."""
    a = [x[k] for x in samples]
    return {"min": min(a), "median": float(np.median(a))}


results = {"machine": machine(), "load_average_start": os.getloadavg(),
           "numba_threads": int(os.environ.get("NUMBA_NUM_THREADS", 0)), "steps": args.steps,
           "repeat": args.repeat, "cases": []}
for n in args.n_side:
    time_dry(n, 20)                         # compile and warm up
    time_wet(n, 20, 10)
    dry, drag, wet = [], [], {e: [] for e in args.every}
    for _ in range(args.repeat):            # interleaved rounds
        dry.append(time_dry(n, args.steps))
        drag.append(time_drag(n, args.steps))
        for every in args.every:
            wet[every].append(time_wet(n, args.steps, every))
    case = {"grains": n**3, "dry_step_s": stats(dry, 0), "dry_step_cpu_s": stats(dry, 1),
            "dry_plus_drag_s": stats(drag, 0), "dry_plus_drag_cpu_s": stats(drag, 1),
            "fluid_step_cpu_s": fluid_step_parts(n, max(args.every)), "wet": []}
    d = case["dry_step_cpu_s"]
    h = {k: case["dry_plus_drag_cpu_s"][k] / d[k] - 1 for k in ("min", "median")}
    case["drag_overhead_cpu"] = h
    for every in args.every:
        row = {"every": every, "step_s": stats(wet[every], 0),
               "step_cpu_s": stats(wet[every], 1)}
        for k, name in ((0, ""), (1, "_cpu")):
            w, dd = stats(wet[every], k), stats(dry, k)
            row["overhead_median" + name] = w["median"] / dd["median"] - 1
            row["overhead_min" + name] = w["min"] / dd["min"] - 1
        case["wet"].append(row)
        print(f"{n**3} grains, fluid every {every}: dry {1e6 * d['min']:.0f} us/step, wet "
              f"{1e6 * row['step_cpu_s']['min']:.0f} us/step (CPU, min): fluid "
              f"+{100 * row['overhead_min_cpu']:.0f} % (min), "
              f"+{100 * row['overhead_median_cpu']:.0f} % (median); wall "
              f"+{100 * row['overhead_min']:.0f} % (min); the drag alone "
              f"+{100 * h['min']:.0f} % (min), +{100 * h['median']:.0f} % (median)", flush=True)
    parts = case["fluid_step_cpu_s"]
    print(f"{n**3} grains, a fluid step {1e3 * parts['total']:.2f} ms CPU: "
          + ", ".join(f"{k} {1e3 * v:.2f}" for k, v in parts.items() if k != "total"),
          flush=True)
    results["cases"].append(case)
results["load_average_end"] = os.getloadavg()
args.out.mkdir(parents=True, exist_ok=True)
(args.out / "results.json").write_text(json.dumps(results, indent=1))
