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

The demo (``--demo-strain``, 0: skip): ``demos/2d/fe2_biaxial.py`` run on 1 and 2 ranks to
that axial strain (16 RVEs of 40 disks in three packings, a weak cell; cut-backs included),
its wall time with and without the consolidation of the packings, and each rank's timers
(RVE relaxations, waiting for the other rank, RVEs moved).

Every case runs ``--repeat`` times, the rank counts interleaved (1, 2, 1, 2, ...), each in a
fresh ``mpiexec``: the cores are shared with other jobs, so the speed-up is taken round by
round (1-rank time over the 2-rank time of the same round) and reported as min / median,
beside the min / median times and the ranks' CPU times (MPICH waits by spinning: a waiting
rank's CPU time counts its wait).

Run: ``python benchmarks/fe2_cost.py`` (GRANFE_SHORT=1: one small mesh, one step, no demo).
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
        wall = time.perf_counter() - t0
        rows.append(dict(seconds=wall, iterations=its,  # the busiest rank's CPU time
                         cpu_seconds=comm.allreduce(time.process_time() - c0, MPI.MAX)))
    per_rank = comm.gather(dict(fe2.stats, points=fe2.n, rves_held=len(fe2.held)), root=0)
    stats = {k: comm.allreduce(v, MPI.SUM) for k, v in fe2.stats.items()}
    rve_busy = comm.allreduce(fe2.stats["rve_seconds"] + fe2.stats["tangent_seconds"], MPI.MAX)
    n_points = comm.allreduce(fe2.n, MPI.SUM)
    if comm.rank == 0:
        wall = sum(r["seconds"] for r in rows)
        out = dict(ranks=comm.size, mesh=list(args.mesh), rves=n_points, particles=proto.sim.p.n,
                   steps=rows, wall_seconds=wall, rve_stats=stats, per_rank=per_rank,
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


def run_case(cmd: list[str], part: Path) -> dict:
    env = dict(os.environ, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1")
    subprocess.run(cmd, check=True, cwd=ROOT, env=env, stdout=subprocess.DEVNULL)
    return json.loads(part.read_text())


def spread(values) -> dict:
    import numpy as np

    return dict(values=list(values), min=float(np.min(values)), median=float(np.median(values)))


def summary(runs: list[dict], key) -> dict:
    """min / median of key(run) per rank count, and of the 1-rank / 2-rank ratio round by
    round."""
    by = {}
    for run in runs:
        by.setdefault(run["ranks"], {})[run["round"]] = key(run)
    out = {str(r): spread(list(v.values())) for r, v in by.items()}
    if 1 in by and 2 in by:
        rounds = sorted(set(by[1]) & set(by[2]))
        out["speedup_2_over_1"] = spread([by[1][k] / by[2][k] for k in rounds])
    return out


def demo_runs(args, out: Path) -> dict:
    """The biaxial demo to args.demo_strain on each rank count, args.repeat interleaved
    rounds."""
    runs = []
    for k in range(args.repeat):
        for ranks in (int(r) for r in args.ranks.split(",")):
            where = out / f"demo_{ranks}_{k}"
            cmd = [str(MPIEXEC), "-n", str(ranks), sys.executable,
                   str(ROOT / "demos/2d/fe2_biaxial.py"), "--strain", str(args.demo_strain),
                   "--out", str(where)]
            d = run_case(cmd, where / "results.json")
            steps = sum(s["seconds"] for s in d["steps"])
            run = dict(ranks=ranks, round=k, wall_seconds=d["wall_seconds"],
                       consolidation_seconds=d["rve_consolidation_seconds"],
                       load_steps_seconds=d["wall_seconds"] - d["rve_consolidation_seconds"],
                       converged_steps_seconds=steps, steps=d["steps"], failures=d["rve_stats"][
                           "failures"] // ranks, per_rank=d["per_rank"],
                       cpu_seconds_max=max(r["cpu_seconds"] for r in d["per_rank"]))
            runs.append(run)
            print(f"demo to {args.demo_strain}, {ranks} rank(s), round {k}: "
                  f"{run['wall_seconds']:.1f} s ({run['consolidation_seconds']:.1f} s "
                  f"consolidation), cpu {run['cpu_seconds_max']:.1f} s", flush=True)
    return dict(strain=args.demo_strain, runs=runs,
                wall=summary(runs, lambda r: r["wall_seconds"]),
                load_steps=summary(runs, lambda r: r["load_steps_seconds"]),
                cpu=summary(runs, lambda r: r["cpu_seconds_max"]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--meshes", default="1x2,2x4,4x4" if not SHORT else "1x1",
                        help="quads across x up, comma separated (two RVEs a quad)")
    parser.add_argument("--ranks", default="1,2", help="rank counts, comma separated")
    parser.add_argument("--steps", type=int, default=1 if SHORT else 3)
    parser.add_argument("--step", type=float, default=5e-4, help="axial strain a load step")
    parser.add_argument("--disks", type=int, default=40)
    parser.add_argument("--tangent", default="secant")
    parser.add_argument("--repeat", type=int, default=1 if SHORT else 3)
    parser.add_argument("--demo-strain", type=float, default=0.0 if SHORT else 0.003,
                        help="axial strain of the demo runs (0: none)")
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
    for mesh in args.meshes.split(",") if args.meshes else []:
        for k in range(args.repeat):
            for ranks in (int(r) for r in args.ranks.split(",")):
                if ranks > 1 and not MPIEXEC.exists():
                    continue
                part = out / f"run_{mesh}_{ranks}_{k}.json"
                cmd = [str(MPIEXEC), "-n", str(ranks), sys.executable, __file__, "--worker",
                       "--mesh", mesh, "--steps", str(args.steps), "--step", str(args.step),
                       "--disks", str(args.disks), "--tangent", args.tangent, "--out", str(part)]
                run = dict(run_case(cmd, part), round=k)
                run["engine_over_fe2"] = engine["median"] / run["rve_particle_steps_per_second"] \
                    * ranks
                run["engine_over_relaxation"] = (engine["median"]
                                                 / run["relaxation_particle_steps_per_core_second"])
                runs.append(run)
                print(f"{run['rves']:4d} RVEs on {ranks} rank(s), round {k}: "
                      f"{run['wall_seconds'] / args.steps:.2f} s a load step, "
                      f"{run['rve_evaluations_per_second']:.1f} RVE evaluations/s, "
                      f"{run['rve_particle_steps_per_second']:.3g} particle-steps/s "
                      f"(engine / FE2 a core: {run['engine_over_fe2']:.2f}; engine / RVE "
                      f"relaxation: {run['engine_over_relaxation']:.2f}), RVEs "
                      f"{100 * run['rve_share_of_wall']:.0f} % of the wall", flush=True)
    meshes = {}
    for run in runs:
        meshes.setdefault("x".join(map(str, run["mesh"])), []).append(run)
    scaling = {m: dict(step_seconds=summary(rs, lambda r: r["wall_seconds"] / len(r["steps"])),
                       step_cpu_seconds=summary(rs, lambda r: sum(
                           s["cpu_seconds"] for s in r["steps"]) / len(r["steps"])))
               for m, rs in meshes.items()}
    demo = demo_runs(args, out) if args.demo_strain > 0 else None
    results = dict(cpu=cpu_model(), cores=os.cpu_count(), inputs=vars(args), engine=engine,
                   runs=runs, scaling=scaling, demo=demo, context=YADE_ESCRIPT,
                   note="2-vCPU VM shared with other sessions (two other engineers' jobs): "
                        "timings are noisy; speed-ups are ratios within one round of "
                        "interleaved runs; the engine is measured before the FE2 runs")
    (out / "results.json").write_text(json.dumps(results, indent=1))
    for run in runs:
        assert run["engine_over_fe2"] > 0
    for m, sc in scaling.items():
        print(f"{m}: seconds a load step " + ", ".join(
            f"{r} rank(s) min {v['min']:.2f} median {v['median']:.2f}"
            for r, v in sc["step_seconds"].items()), flush=True)
    if demo:
        for what in ("wall", "load_steps", "cpu"):
            print(f"demo {what}: " + ", ".join(f"{r}: min {v['min']:.2f} median {v['median']:.2f}"
                                               for r, v in demo[what].items()), flush=True)


if __name__ == "__main__":
    main()
