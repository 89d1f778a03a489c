"""Cost of two-scale FE x DEM (`coupling.fe2`): RVE throughput against the number of RVEs and
ranks, and against the DEM engine on the same grains.

Measured, for each rank count (1, 2) and mesh (``--meshes``: quads across x up, two
triangles a quad, one RVE a triangle), in a fresh ``mpiexec -n R`` worker: the biaxial
test of ``tests/coupling/test_fe2.py`` (rollers, confinement p0 on one side, the top moved
down) for ``--steps`` load steps of ``--step`` axial strain, Newton with the secant tangent
(`MacroNewton(tangent="secant")`). Per load step: wall time, Newton iterations; over the
run: RVE evaluations (one RVE relaxed to one strain increment) per second, the RVEs' DEM
steps per second (summed over ranks) and their particle-steps per second, the share of the
wall time spent in the RVEs (relaxations and tangents; the rest is the macro side:
assembly, LU, fills, waiting for the other rank).
The consolidation of the one prototype cell is left out (every point is a clone).

Reference on the same grains: the DEM engine alone (`dem.Simulation.step(n)`, the clone of
the same consolidated cell driven by a constant velocity gradient, no servo, no damping),
particle-steps per second, min / median of ``--repeat`` runs. Two ratios: engine / RVE
relaxation (the DEM steps inside `RVE.load` over the time spent there, per core: the cost of
the quasi-static driver, one ``step(1)`` call a step with the damping between) and engine /
FE2 (the RVEs' DEM steps over the whole wall time of the load steps, per core: tangents,
restores, the macro side and the waiting of ranks included). Target: within 2x.

Context (the brief's figure for YADE + Escript, Guo & Zhao): 8192 RVEs, about 4.5 days on 16
processes for a triaxial test, 1.4e3 core-seconds per RVE for the whole test; ours per RVE
for the measured steps is in ``results.json`` with the steps it covers (the two are not the
same test: particle counts, dimensions and step counts differ; the per-particle-step figure
is the comparable one, and we do not know theirs).

Run: ``python benchmarks/fe2_cost.py`` (GRANFE_SHORT=1: one small mesh, one step).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from machine import cpu_model

SHORT = os.environ.get("GRANFE_SHORT") == "1"
ROOT = Path(__file__).resolve().parents[1]
MPIEXEC = Path(sys.executable).parent / "mpiexec"
P0 = 1.0e5  # [Pa]
YADE_ESCRIPT = dict(rves=8192, processes=16, days=4.5, test="triaxial",
                    core_seconds_per_rve=4.5 * 86400 * 16 / 8192,
                    source="the issue's context figure (YADE + Escript FEM x DEM, Guo & Zhao)")




def settings(args):
    from dem.rve import Grains, QuasiStatic

    grains = Grains(n=args.disks, dim=2, kn=1e8, kt=7e7, friction=0.5, seed=1,
                    consolidation_friction=0.1)
    solver = QuasiStatic(force_tol=1e-3, stress_tol=2e-3, ramp_steps=200, strain_rate=2e-6)
    return grains, solver


def worker(args) -> None:
    """One mesh on this MPI world: the biaxial steps, timings to args.out (rank 0)."""
    import dolfinx_solver  # noqa: F401
    from mpi4py import MPI

    import numpy as np
    from dolfinx import mesh

    from coupling.fe2 import FE2, MacroNewton
    from dem.rve import RVE
    from granfe.models.quadrature_stress import QuadratureStress, QuadratureStressMaterial
    from granfe.problem import ContinuumProblem

    comm = MPI.COMM_WORLD
    grains, solver = settings(args)
    proto = RVE.consolidate(grains, P0, solver)
    nx, ny = args.mesh
    height = 2.0
    dom = mesh.create_rectangle(comm, [[0, 0], [1, height]], [nx, ny], mesh.CellType.triangle)
    p = ContinuumProblem(dom, QuadratureStress(QuadratureStressMaterial()), quadrature_degree=1,
                         solver="redundant", prefix="fe2cost_")
    p.fix(lambda x: np.isclose(x[1], 0.0), "u_y")
    p.fix(lambda x: np.isclose(x[0], 0.0), "u_x")
    top = p.fix(lambda x: np.isclose(x[1], height), "u_y", 0.0)
    p.traction(lambda x: np.isclose(x[0], 1.0), (-P0, 0.0))
    fe2 = FE2(p, [proto], settings=MacroNewton(force_tol=1e-3, tangent=args.tangent,
                                               tangent_every=1000))
    comm.barrier()
    rows = []
    for k in range(args.steps):
        top.value = -(k + 1) * args.step * height
        comm.barrier()
        t0, c0 = time.perf_counter(), time.process_time()
        its = fe2.solve()
        comm.barrier()
        rows.append(dict(seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - c0,
                         iterations=its))
    stats = {k: comm.allreduce(v, MPI.SUM) for k, v in fe2.stats.items()}
    rve_busy = comm.allreduce(fe2.stats["rve_seconds"] + fe2.stats["tangent_seconds"], MPI.MAX)
    n_points = comm.allreduce(fe2.n, MPI.SUM)
    if comm.rank == 0:
        wall = sum(r["seconds"] for r in rows)
        out = dict(ranks=comm.size, mesh=list(args.mesh), rves=n_points, particles=proto.sim.p.n,
                   steps=rows, wall_seconds=wall, rve_stats=stats,
                   rve_evaluations_per_second=stats["rve_evaluations"] / wall,
                   rve_dem_steps_per_second=stats["rve_steps"] / wall,
                   rve_particle_steps_per_second=stats["rve_steps"] * proto.sim.p.n / wall,
                   # per core, over the time inside the RVE relaxations only (tangents out)
                   relaxation_particle_steps_per_core_second=(
                       stats["rve_steps"] * proto.sim.p.n / stats["rve_seconds"]),
                   rve_share_of_wall=rve_busy / wall,
                   core_seconds_per_rve=wall * comm.size / n_points)
        Path(args.out).write_text(json.dumps(out))


def engine_rate(args) -> dict:
    """Particle-steps/s of Simulation.step(n) on a clone of the same consolidated cell."""
    import numpy as np

    from coupling.fe2 import clone_rve
    from dem.rve import RVE, from_mandel

    grains, solver = settings(args)
    proto = RVE.consolidate(grains, P0, solver)
    n_steps = 200 if SHORT else 2000
    rates = []
    for _ in range(args.repeat + 1):  # the first one compiles
        c = clone_rve(proto)
        c.sim.cell.velocity_gradient[:] = from_mandel(np.array([3e-4, -1e-3, 0.0])
                                                      / (n_steps * c.sim.dt), 2)
        t0 = time.perf_counter()
        c.sim.step(n_steps)
        rates.append(n_steps * c.sim.p.n / (time.perf_counter() - t0))
    rates = rates[1:]
    return dict(particles=int(proto.sim.p.n), steps=n_steps, particle_steps_per_second=rates,
                min=float(min(rates)), median=float(np.median(rates)), max=float(max(rates)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--meshes", default="1x2,2x4,4x4" if not SHORT else "1x1",
                        help="quads across x up, comma separated (two RVEs a quad)")
    parser.add_argument("--ranks", default="1,2", help="rank counts, comma separated")
    parser.add_argument("--steps", type=int, default=1 if SHORT else 3)
    parser.add_argument("--step", type=float, default=5e-4, help="axial strain a load step")
    parser.add_argument("--disks", type=int, default=40)
    parser.add_argument("--tangent", default="secant")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--mesh", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--out", default="output/fe2_cost")
    args = parser.parse_args()
    if args.worker:
        args.mesh = tuple(int(v) for v in args.mesh.split("x"))
        worker(args)
        return
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    engine = engine_rate(args)
    print(f"engine: {engine['median']:.3g} particle-steps/s (median of {args.repeat}, "
          f"{engine['particles']} disks)", flush=True)
    runs = []
    for mesh in args.meshes.split(","):
        for ranks in (int(r) for r in args.ranks.split(",")):
            if ranks > 1 and not MPIEXEC.exists():
                continue
            part = out / f"run_{mesh}_{ranks}.json"
            cmd = [str(MPIEXEC), "-n", str(ranks), sys.executable, __file__, "--worker",
                   "--mesh", mesh, "--steps", str(args.steps), "--step", str(args.step),
                   "--disks", str(args.disks), "--tangent", args.tangent, "--out", str(part)]
            env = dict(os.environ, NUMBA_NUM_THREADS="1")
            subprocess.run(cmd, check=True, cwd=ROOT, env=env)
            run = json.loads(part.read_text())
            run["engine_over_fe2"] = engine["median"] / run["rve_particle_steps_per_second"] \
                * ranks
            run["engine_over_relaxation"] = (engine["median"]
                                             / run["relaxation_particle_steps_per_core_second"])
            runs.append(run)
            print(f"{run['rves']:4d} RVEs on {ranks} rank(s): "
                  f"{run['wall_seconds'] / args.steps:.2f} s a load step, "
                  f"{run['rve_evaluations_per_second']:.1f} RVE evaluations/s, "
                  f"{run['rve_particle_steps_per_second']:.3g} particle-steps/s "
                  f"(engine / FE2 a core: {run['engine_over_fe2']:.2f}; engine / RVE "
                  f"relaxation: {run['engine_over_relaxation']:.2f}), RVEs "
                  f"{100 * run['rve_share_of_wall']:.0f} % of the wall", flush=True)
    results = dict(cpu=cpu_model(), cores=os.cpu_count(), inputs=vars(args), engine=engine,
                   runs=runs, context=YADE_ESCRIPT,
                   note="2-vCPU VM shared with other sessions: timings are noisy; the engine "
                        "and the FE2 runs are measured at different moments")
    (out / "results.json").write_text(json.dumps(results, indent=1))
    for run in runs:
        assert run["engine_over_fe2"] > 0


if __name__ == "__main__":
    main()
