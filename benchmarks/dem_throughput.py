"""DEM throughput: the peers' "settle" scene, numba `dem` against LIGGGHTS.

This benchmark shows how to:
- build the settle scene of ``../shared/peers`` (``tools/params.py``: jittered simple-cubic
  lattice of quartz-like spheres, E = 2.9e7 Pa, Hertz-Mindlin + friction 0.5 + restitution
  damping 0.5 with clipped normal force, five walls, gravity, dt = 0.2 Rayleigh step,
  2000 steps, skin 0.2 mm) with the `dem` API,
- measure particle-steps per second on 1 and 2 numba threads (3 repeats interleaved, min
  and median; loop time only, JIT excluded) and their ratio, contacts per step, JIT compile time cold (fresh
  NUMBA_CACHE_DIR) and warm, and the kinetic energy at step 2000,
- the same on 1 and 2 MPI ranks (`dem.DistributedSimulation`, one numba thread per rank,
  launched as ``mpiexec -n P python dem_throughput.py --mpi-worker N REPEATS``; loop time =
  slowest rank), with the number of decompositions, migrations and halo copies, and the
  difference of its KE(2000) from the serial run's (0 when the runs agree bit for bit),
- compare with LIGGGHTS: run here if the ``liggghts`` binary exists, else the peers'
  measured numbers from RESULTS.md (said so in results.json).

Run: ``python benchmarks/dem_throughput.py [--out DIR]``; ``GRANFE_SHORT=1``: N = 10,000 only.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# ---------------------------------------------------------------- parameters
PEERS = Path(os.environ.get("GRANFE_PEERS", "/work/shared/peers"))
SHORT = os.environ.get("GRANFE_SHORT", "0") == "1"
NS = [10_000] if SHORT else [10_000, 50_000]
THREADS = [1, 2]
REPEATS = 3
NSTEPS = 2000
# peers' RESULTS.md §1 (LIGGGHTS 3.8.0, this machine type, run 1): median (best) M p-steps/s
LIGGGHTS_RESULTS = {
    10_000: dict(mps={1: (13.8, 14.0), 2: (24.6, 24.9)}, ke_2000=6.9388e-4,
                 contacts={500: 76, 1000: 1282, 1500: 4016, 2000: 8275}),
    50_000: dict(mps={1: (12.9, 13.4), 2: (22.8, 24.9)}, ke_2000=3.4135e-3,
                 contacts={500: 423, 1000: 6466, 1500: 20421, 2000: 41468}),
}


def peers_params():
    spec = importlib.util.spec_from_file_location("peers_params", PEERS / "tools/params.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def settle_scene(P, n):
    """The settle scene of peers/tools/params.py: particles, material, walls, keywords."""
    import dem

    s = P.settle_params()
    pos, lx, ly, _ = P.lattice(n)
    mat = dem.ContactMaterial(E=s["E"], nu=s["NU"], density=s["RHO"], friction=s["MU"],
                              restitution=s["COR"], limit_force=True)
    walls = [dem.PlaneWall((0, 0, 0), (0, 0, 1)), dem.PlaneWall((0, 0, 0), (1, 0, 0)),
             dem.PlaneWall((lx, 0, 0), (-1, 0, 0)), dem.PlaneWall((0, 0, 0), (0, 1, 0)),
             dem.PlaneWall((0, ly, 0), (0, -1, 0))]
    p = dem.Particles.spheres(pos, s["R"], s["RHO"])
    return p, mat, walls, dict(gravity=(0, 0, -s["G"]), dt=s["DT"], skin=s["SKIN"])


def settle_sim(P, n):
    """The settle scene as a `dem.Simulation`."""
    import dem

    p, mat, walls, kw = settle_scene(P, n)
    return dem.Simulation(p, mat, walls, **kw)


def mpi_worker(n, repeats):
    """Runs under mpiexec: the settle scene as a `dem.DistributedSimulation`; rank 0
    prints a JSON line (loop time of the slowest rank)."""
    from mpi4py import MPI

    import dem

    comm = MPI.COMM_WORLD
    P = peers_params()
    loops = []
    for _ in range(repeats):
        p, mat, walls, kw = settle_scene(P, n)
        sim = dem.DistributedSimulation(p if comm.rank == 0 else None, mat, walls, **kw)
        sim.step(1)  # JIT (cached) and the first decomposition outside the timing
        comm.Barrier()
        t = time.perf_counter()
        sim.step(NSTEPS - 1)
        loops.append(comm.allreduce(time.perf_counter() - t, op=MPI.MAX) * NSTEPS
                     / (NSTEPS - 1))
    ke = sim.energy()["kinetic_translational"]
    halo = comm.gather(int((~sim.owned).sum()), root=0)
    if comm.rank == 0:
        print(json.dumps(dict(loops=loops, ke_2000=ke, decompositions=sim.decompositions,
                              migrated=sim.migrated, halo_copies=halo)))


def run_mpi_worker(n, procs, repeats):
    env = dict(os.environ, NUMBA_NUM_THREADS="1")
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    mpiexec = str(Path(sys.executable).parent / "mpiexec")
    out = subprocess.run([mpiexec, "-n", str(procs), sys.executable, __file__, "--mpi-worker",
                          str(n), str(repeats)], env=env, check=True, capture_output=True,
                         text=True, cwd=root)
    return json.loads(out.stdout.strip().splitlines()[-1])


def worker(n, repeats, count):
    """Runs in a subprocess with NUMBA_NUM_THREADS set: prints a JSON line."""
    t0 = time.perf_counter()
    P = peers_params()
    sim = settle_sim(P, n)
    sim.step(1)
    first = time.perf_counter() - t0
    loops, ke = [], None
    for _ in range(repeats):
        sim = settle_sim(P, n)
        t = time.perf_counter()
        sim.step(NSTEPS)
        loops.append(time.perf_counter() - t)
        ke = sim.energy()["kinetic_translational"]
    contacts = {}
    if count:
        sim = settle_sim(P, n)
        for _k in range(NSTEPS // 100):
            sim.step(100)
            contacts[sim.nsteps] = len(sim.contacts()[0])
    import numba

    try:
        layer = numba.threading_layer()
    except ValueError:  # no parallel region ran (one thread: the serial kernels)
        layer = "none"
    print(json.dumps(dict(loops=loops, ke_2000=ke, contacts=contacts, builds=sim.nl.builds,
                          first_step_s=first, layer=layer)))


def run_worker(n, threads, repeats, count, cache_dir=None):
    env = dict(os.environ, NUMBA_NUM_THREADS=str(threads))
    if cache_dir:
        env["NUMBA_CACHE_DIR"] = cache_dir
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    out = subprocess.run([sys.executable, __file__, "--worker", str(n), str(repeats),
                          str(int(count))], env=env, check=True, capture_output=True,
                         text=True, cwd=root)
    return json.loads(out.stdout.strip().splitlines()[-1])


def run_liggghts(P, n, procs, workdir):
    """Loop time [s] of LIGGGHTS on the settle scene, or None if it is not installed."""
    exe = shutil.which("liggghts") or shutil.which("lmp_serial")
    if exe is None:
        return None
    s = P.settle_params()
    subprocess.run([sys.executable, str(PEERS / "tools/gen_scene.py"), str(n), workdir],
                   check=True, capture_output=True)
    _, lx, ly, _ = P.lattice(n)
    var = dict(datafile=f"{workdir}/settle_{n}.data", dt=s["DT"], nsteps=NSTEPS, E=s["E"],
               nu=s["NU"], cor=s["COR"], mu=s["MU"], skin=s["SKIN"], Lx=lx, Ly=ly, diag=0)
    cmd = [exe, "-in", str(PEERS / "liggghts/in.settle")]
    for k, v in var.items():
        cmd += ["-var", k, repr(v)]
    if procs > 1:
        cmd = ["mpirun", "-np", str(procs), "--allow-run-as-root"] + cmd
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=workdir)
    return float(re.search(r"Loop time of ([0-9.eE+-]+)", out.stdout).group(1))


def bar_plot(res, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    labels, w = [], 0.2
    for k, n in enumerate(res["N"]):
        r = res["runs"][str(n)]
        src = "" if r["liggghts"]["1"]["source"] == "run here" else " (RESULTS.md)"
        bars = [("dem 1 thread", r["dem"]["1"]["mps_median"]),
                ("dem 2 threads", r["dem"]["2"]["mps_median"]),
                ("dem MPI 1 rank", r["dem_mpi"]["1"]["mps_median"]),
                ("dem MPI 2 ranks", r["dem_mpi"]["2"]["mps_median"]),
                ("LIGGGHTS 1 proc" + src, r["liggghts"]["1"]["mps_median"]),
                ("LIGGGHTS 2 procs" + src, r["liggghts"]["2"]["mps_median"])]
        w = 0.8 / len(bars)
        for b, (lab, val) in enumerate(bars):
            off = (b - (len(bars) - 1) / 2) * w
            ax.bar(k + off, val, w, color=f"C{b}", label=lab if k == 0 else None)
            ax.text(k + off, val, f"{val:.1f}", ha="center", va="bottom", fontsize=7)
        labels.append(f"N = {n:,}")
    ax.set_xticks(range(len(labels)), labels)
    ax.set_ylabel("M particle-steps / s (median of 3)")
    ax.set_title("settle scene, 2000 steps: numba dem (threads, MPI ranks) vs LIGGGHTS")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="output/dem_throughput/")
    ap.add_argument("--worker", nargs=3, type=int, help=argparse.SUPPRESS)
    ap.add_argument("--mpi-worker", nargs=2, type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        return worker(*args.worker)
    if args.mpi_worker:
        return mpi_worker(*args.mpi_worker)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    P = peers_params()
    res = dict(scene="peers settle (tools/params.py settle_params, lattice)", N=NS,
               nsteps=NSTEPS, repeats=REPEATS, params=P.settle_params(), runs={})

    # ---------------------------------------------------------------- JIT compile time
    with tempfile.TemporaryDirectory() as cache:
        cold = run_worker(NS[0], 1, 0, False, cache)["first_step_s"]
        warm = run_worker(NS[0], 1, 0, False, cache)["first_step_s"]
    res["jit"] = dict(cold_s=cold, warm_s=warm, note="import + scene + first step, "
                      f"N={NS[0]}, fresh NUMBA_CACHE_DIR then the same one again")
    print(f"JIT: cold {cold:.1f} s, warm {warm:.2f} s (import + set-up + first step)")

    # ---------------------------------------------------------------- timed runs
    with tempfile.TemporaryDirectory() as work:
        for n in NS:
            ref = LIGGGHTS_RESULTS[n]
            rn = dict(dem={}, liggghts={})
            # 1 and 2 threads interleaved, one repeat each in turn, so that a change of
            # machine load hits both alike
            runs = {th: [] for th in THREADS}
            for r in range(REPEATS):
                for th in THREADS:
                    runs[th].append(run_worker(n, th, 1, th == 1 and r == 0))
            for th in THREADS:
                loops = [w["loops"][0] for w in runs[th]]
                w = runs[th][-1]
                mps = [n * NSTEPS / t / 1e6 for t in loops]
                rn["dem"][str(th)] = dict(loop_s=loops, mps_min=min(mps),
                                          mps_median=float(np.median(mps)),
                                          mps_best=max(mps), ke_2000=w["ke_2000"],
                                          neighbour_builds=w["builds"],
                                          threading_layer=w["layer"])
                if runs[th][0]["contacts"]:
                    rn["contacts"] = runs[th][0]["contacts"]
                print(f"N={n} dem {th} thread(s): {np.median(mps):.2f} M p-steps/s "
                      f"(min {min(mps):.2f}), KE(2000) = {w['ke_2000']:.5e} J")
            rn["speedup_2_threads"] = rn["dem"]["2"]["mps_median"] / rn["dem"]["1"]["mps_median"]
            rn["ke_2000_2_threads_equal_1_thread"] = rn["dem"]["2"]["ke_2000"] == \
                rn["dem"]["1"]["ke_2000"]
            rn["dem_mpi"] = {}
            for procs in THREADS:
                w = run_mpi_worker(n, procs, REPEATS)
                mps = [n * NSTEPS / t / 1e6 for t in w["loops"]]
                ke_diff = w["ke_2000"] / rn["dem"]["1"]["ke_2000"] - 1
                rn["dem_mpi"][str(procs)] = dict(
                    loop_s=w["loops"], mps_min=min(mps), mps_median=float(np.median(mps)),
                    mps_best=max(mps), ke_2000=w["ke_2000"], ke_2000_rel_diff_serial=ke_diff,
                    decompositions=w["decompositions"], migrated=w["migrated"],
                    halo_copies_per_rank=w["halo_copies"])
                print(f"N={n} dem MPI {procs} rank(s) x 1 thread: {np.median(mps):.2f} M "
                      f"p-steps/s (min {min(mps):.2f}), KE(2000) - serial: {ke_diff:+.1e}, "
                      f"{w['decompositions']} decompositions, {w['migrated']} migrations, "
                      f"halo copies per rank {w['halo_copies']}")
            for procs in THREADS:
                loop = run_liggghts(P, n, procs, work)
                if loop is None:
                    med, best = ref["mps"][procs]
                    rn["liggghts"][str(procs)] = dict(
                        mps_median=med, mps_best=best,
                        source="peers RESULTS.md §1 (liggghts binary not found here)")
                else:
                    m = n * NSTEPS / loop / 1e6
                    rn["liggghts"][str(procs)] = dict(mps_median=m, mps_best=m,
                                                      source="run here", loop_s=loop)
            d1 = rn["dem"]["1"]
            rn["ratio_dem_over_liggghts_1core"] = d1["mps_median"] / rn["liggghts"]["1"][
                "mps_median"]
            rn["ratio_dem_over_liggghts_2cores"] = rn["dem"]["2"]["mps_median"] / \
                rn["liggghts"]["2"]["mps_median"]
            rn["speedup_2_ranks"] = rn["dem_mpi"]["2"]["mps_median"] / d1["mps_median"]
            rn["ke_2000_liggghts"] = ref["ke_2000"]
            rn["ke_2000_rel_diff"] = d1["ke_2000"] / ref["ke_2000"] - 1
            rn["contacts_liggghts"] = ref["contacts"]
            c = rn["contacts"]
            rn["contacts_mean_per_step"] = float(np.mean(list(c.values())))
            res["runs"][str(n)] = rn
            print(f"N={n}: 2 threads / 1 = {rn['speedup_2_threads']:.2f}, 2 ranks / 1 thread "
                  f"= {rn['speedup_2_ranks']:.2f}, dem/LIGGGHTS 2 cores = "
                  f"{rn['ratio_dem_over_liggghts_2cores']:.2f}")
            print(f"N={n}: dem/LIGGGHTS (1 core) = {rn['ratio_dem_over_liggghts_1core']:.2f}"
                  f", KE diff {rn['ke_2000_rel_diff']:+.2e}, contacts at 2000: "
                  f"{c[str(NSTEPS)] if str(NSTEPS) in c else c[NSTEPS]} vs "
                  f"{ref['contacts'][2000]}")

    from dem import forces, integrate, neighbours

    res["dem_parallel_thresholds"] = dict(
        pair_candidates=forces.PARALLEL_MIN, kick_drift_particles=integrate.KD_PARALLEL_MIN,
        neighbour_build_particles=neighbours.PAIRS_PARALLEL_MIN,
        wall_candidates=forces.WALL_PARALLEL_MIN,
        note="with more than one numba thread the prange drivers run from these sizes on; "
             "below them the 2-thread run uses the serial kernels (same bits either way)")
    res["load_average_at_end"] = os.getloadavg()
    res["machine_note"] = ("2-vCPU VM shared with other jobs: compare medians and rerun; the "
                           "LIGGGHTS numbers from RESULTS.md were measured on an idle machine")
    (out / "results.json").write_text(json.dumps(res, indent=1, default=str))
    bar_plot(res, out / "throughput.png")
    print(f"wrote {out / 'results.json'} and {out / 'throughput.png'}")

    # ---------------------------------------------------------------- checks
    for n in NS:
        rn = res["runs"][str(n)]
        c = rn["contacts"]
        c2000 = c[str(NSTEPS)] if str(NSTEPS) in c else c[NSTEPS]
        assert abs(rn["ke_2000_rel_diff"]) < 0.02, "KE(2000) departs from LIGGGHTS by > 2 %"
        assert abs(c2000 / LIGGGHTS_RESULTS[n]["contacts"][2000] - 1) < 0.02


if __name__ == "__main__":
    main()
