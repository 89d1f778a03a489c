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
  measured numbers from RESULTS.md (said so in results.json),
- dense window-size scenes (grains in lasting contact, what a coupled DE window holds):
  touching simple-cubic sphere lattices (the settle scene's lattice at spacing 2R, no
  jitter: Hertz-Mindlin, walls, gravity) and touching hexagonal disk lattices (linear law,
  the `make demo` grains: R = 1.5 mm, kn = 2e5 N/m, kt = kn/2), N = 1k, 2k, 5k, settling
  under gravity from rest; one numba thread against LIGGGHTS on one process on the same
  3D lattices in the same invocation (interleaved repeats),
- with ``--before DIR`` (a directory holding another version's ``dem`` package, e.g.
  ``git archive <commit> dem | tar -x -C DIR``), the dense scenes and the fixed cost run
  on that version too, in the same rounds (before, after, LIGGGHTS; interleaved repeats),
  and their speed-up is recorded,
- record the machine: CPU model and flags, the LLVM target numba compiles for.

Run: ``python benchmarks/dem_throughput.py [--out DIR] [--scenes settle,dense] [--before DIR]``;
``GRANFE_SHORT=1``: N = 10,000 only for the settle scene, one repeat of the dense ones.
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
DENSE_NS = [1000, 2000, 5000]
DENSE_STEPS = 2000
DENSE_REPEATS = 1 if SHORT else 3
IDLE_N = 512
DISK = dict(R=1.5e-3, RHO=2650.0, KN=2.0e5, KT=1.0e5, MU=0.5, COR=0.5, E=1e8, NU=0.25,
            G=9.81)
"""2D disks of scenes/cpt_2d.toml (linear law; E, nu only enter the time step bound)."""
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
    p = dem.Particles.spheres(pos, s["R"], s["RHO"])
    return p, settle_material(s), open_box(lx, ly), dict(gravity=(0, 0, -s["G"]), dt=s["DT"], skin=s["SKIN"])


def settle_material(s):
    """The peers' Hertz-Mindlin material of the settle scene's parameters ``s``."""
    import dem

    return dem.ContactMaterial(E=s["E"], nu=s["NU"], density=s["RHO"], friction=s["MU"],
                               restitution=s["COR"], limit_force=True)


def open_box(lx, ly):
    """Floor and four side walls of an ``lx`` x ``ly`` box open at the top."""
    import dem

    return [dem.PlaneWall((0, 0, 0), (0, 0, 1)), dem.PlaneWall((0, 0, 0), (1, 0, 0)),
            dem.PlaneWall((lx, 0, 0), (-1, 0, 0)), dem.PlaneWall((0, 0, 0), (0, 1, 0)),
            dem.PlaneWall((0, ly, 0), (0, -1, 0))]


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


# ---------------------------------------------------------------- dense scenes
def dense_lattice(P, n):
    """The settle scene's simple-cubic lattice at spacing 2R and no jitter: every sphere
    touches its neighbours (positions, box Lx, Ly)."""
    pos, lx, ly, _ = P.lattice(n, spacing=2.0 * P.R, jitter=0.0)
    return pos, lx, ly


def dense_sim(P, kind, n):
    """A dense scene as a `dem.Simulation`: kind "3d" (touching sphere lattice, the settle
    scene's material, walls and time step), "2d" (touching hexagonal disk lattice of N
    disks in a box, linear law, automatic time step) or "idle" (spheres 0.1 mm apart in a
    closed box, no gravity: neighbour candidates and wall candidates but no contact, the
    fixed cost of a step)."""
    import dem
    from dem.packing import lattice_packing

    if kind == "idle":  # n spheres on a lattice 0.1 mm apart: candidates, no contact
        s = P.settle_params()
        pos, lx, ly, _ = P.lattice(n, spacing=2.1 * P.R, jitter=0.0, nz=8)
        walls = dem.box_walls((0, 0, 0), (lx, ly, pos[:, 2].max() + P.R * 1.1))
        p = dem.Particles.spheres(pos, s["R"], s["RHO"])
        return dem.Simulation(p, settle_material(s), walls, (0, 0, 0), dt=s["DT"], skin=s["SKIN"])
    if kind == "3d":
        s = P.settle_params()
        pos, lx, ly = dense_lattice(P, n)
        p = dem.Particles.spheres(pos, s["R"], s["RHO"])
        return dem.Simulation(p, settle_material(s), open_box(lx, ly), (0, 0, -s["G"]), dt=s["DT"],
                              skin=s["SKIN"])
    d = DISK
    ncol = int(np.ceil(np.sqrt(n / 0.866)))  # a square-ish bed
    width = (ncol + 0.5) * 2 * d["R"]
    height = (int(np.ceil(n / ncol)) + 1) * np.sqrt(3.0) * d["R"] + 2 * d["R"]
    x, _ = lattice_packing((0, 0), (width, height), d["R"], kind="hex")
    if len(x) < n:
        raise ValueError(f"2D dense scene: {len(x)} lattice sites for {n} disks")
    x = x[np.lexsort((x[:, 0], x[:, 1]))][:n]  # the lowest n rows, bottom up
    mat = dem.ContactMaterial(E=d["E"], nu=d["NU"], density=d["RHO"], friction=d["MU"],
                              restitution=d["COR"], law="linear", kn=d["KN"], kt=d["KT"])
    p = dem.Particles.spheres(x, d["R"], d["RHO"], dim=2)
    walls = dem.box_walls((0, 0, 0), (width, 2 * height, 0), dim=2)
    return dem.Simulation(p, mat, walls, (0, -d["G"], 0))


def dense_worker(kind, n, repeats):
    """Runs in a subprocess with NUMBA_NUM_THREADS set: prints a JSON line (loop times of
    DENSE_STEPS steps from rest, contacts per particle at the end, KE)."""
    P = peers_params()
    dense_sim(P, kind, n).step(1)  # JIT (cached) outside the timing
    loops, cpu = [], []
    for _ in range(repeats):
        sim = dense_sim(P, kind, n)
        t, c = time.perf_counter(), time.process_time()
        sim.step(DENSE_STEPS)
        loops.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    print(json.dumps(dict(loops=loops, cpu=cpu, n=sim.p.n, dt=sim.dt, builds=sim.nl.builds,
                          contacts_end=len(sim.contacts()[0]),
                          wall_candidates_end=len(sim.nl.wi),
                          ke_end=sim.energy()["kinetic_translational"])))


def run_dense_worker(kind, n, threads, repeats, root=None):
    """`dense_worker` in a subprocess, on the ``dem`` package under ``root`` (default: this
    repository's)."""
    env = dict(os.environ, NUMBA_NUM_THREADS=str(threads))
    root = str(root or Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    out = subprocess.run([sys.executable, __file__, "--dense-worker", kind, str(n),
                          str(repeats)], env=env, check=True, capture_output=True, text=True,
                         cwd=root)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _children_cpu():
    import resource

    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run_liggghts_dense(P, n, workdir, diag=False, nsteps=DENSE_STEPS):
    """LIGGGHTS (peers' in.settle) on the dense 3D lattice for nsteps: (loop time [s],
    thermo rows (step, ke, contacts if diag), CPU time of the whole process [s]), or None
    if it is not installed."""
    exe = shutil.which("liggghts") or shutil.which("lmp_serial")
    if exe is None:
        return None
    s = P.settle_params()
    pos, lx, ly = dense_lattice(P, n)
    lz = (pos[:, 2].max() + 3 * P.R)
    data = Path(workdir) / f"dense_{n}.data"
    with open(data, "w") as f:  # peers' gen_scene.py format
        f.write(f"dense lattice N={n} spacing=2R jitter=0\n\n{n} atoms\n1 atom types\n\n")
        f.write(f"0.0 {lx:.17g} xlo xhi\n0.0 {ly:.17g} ylo yhi\n0.0 {lz:.17g} zlo zhi\n\n")
        f.write("Atoms\n\n")
        for i, (x, y, z) in enumerate(pos, start=1):
            f.write(f"{i} 1 {2 * P.R:.17g} {P.RHO:.17g} {x:.17g} {y:.17g} {z:.17g}\n")
    var = dict(datafile=str(data), dt=s["DT"], nsteps=nsteps, E=s["E"], nu=s["NU"],
               cor=s["COR"], mu=s["MU"], skin=s["SKIN"], Lx=lx, Ly=ly, diag=int(diag))
    cmd = [exe, "-in", str(PEERS / "liggghts/in.settle")]
    for k, v in var.items():
        cmd += ["-var", k, repr(float(v)) if isinstance(v, float) else str(v)]
    c0 = _children_cpu()
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=workdir)
    cpu = _children_cpu() - c0
    loop = float(re.search(r"Loop time of ([0-9.eE+-]+)", out.stdout).group(1))
    rows = re.findall(r"^\s+(\d+)\s+\d+\s+(\S+)\s+\S+\s+(\S+)\s+\S+\s*$", out.stdout,
                      re.MULTILINE) if diag else []
    return loop, [(int(a), float(b), float(c)) for a, b, c in rows], cpu


def machine_info():
    """CPU model and flags, the LLVM target numba compiles for, versions."""
    import llvmlite
    import llvmlite.binding as ll
    import numba

    feats = numba.config.CPU_FEATURES or ",".join(
        f[1:] for f in ll.get_host_cpu_features().flatten().split(",") if f.startswith("+"))
    info = dict(numba=numba.__version__, llvmlite=llvmlite.__version__,
                numba_target_cpu=numba.config.CPU_NAME or ll.get_host_cpu_name(),
                numba_target_features=feats,
                python=sys.version.split()[0], cores=os.cpu_count())
    try:
        cpu = Path("/proc/cpuinfo").read_text()
        info["cpu_model"] = re.search(r"^model name\s*:\s*(.*)$", cpu, re.MULTILINE).group(1)
        info["cpu_flags"] = re.search(r"^flags\s*:\s*(.*)$", cpu, re.MULTILINE).group(1)
        mhz = re.search(r"^cpu MHz\s*:\s*(.*)$", cpu, re.MULTILINE)
        info["cpu_mhz"] = float(mhz.group(1)) if mhz else None
    except (OSError, AttributeError):
        import platform

        info["cpu_model"] = platform.processor()
    avx = [f for f in ("avx2", "avx512f", "fma") if f in info.get("cpu_flags", "").split()]
    info["simd"] = avx
    exe = shutil.which("liggghts")
    if exe:
        out = subprocess.run([exe, "-log", "none"], input="", capture_output=True, text=True,
                             cwd=tempfile.gettempdir())
        m = re.search(r"LIGGGHTS \(Version ([^,]*)", out.stdout)
        info["liggghts"] = m.group(1) if m else exe
    return info


def _before_record(loops, now_loops, n):
    """Loop times of the ``--before`` version and its speed-up to this one (medians)."""
    mps = [n * DENSE_STEPS / t / 1e6 for t in loops]
    return dict(loop_s=loops, mps_median=float(np.median(mps)), mps_best=max(mps),
                speedup_median=float(np.median(loops) / np.median(now_loops)),
                speedup_best=float(min(loops) / min(now_loops)))


def run_dense(res, P, work, before=None):
    """Dense scenes: dem on one numba thread, LIGGGHTS on one process (3D), interleaved;
    with ``before`` (a directory holding another ``dem``) that version in the same rounds."""
    dense = dict(steps=DENSE_STEPS, repeats=DENSE_REPEATS, scenes={},
                 note="from rest: touching lattices settle under gravity for "
                      f"{DENSE_STEPS} steps; M particle-steps/s = N x steps / loop time, "
                      "JIT excluded; one numba thread (NUMBA_NUM_THREADS=1) and one "
                      "LIGGGHTS process, repeats interleaved; cpu_s / cpu_loop_s: the "
                      "CPU time of dem's loop (process_time) and of LIGGGHTS's (its run's "
                      "less a run of 0 steps), ratio_dem_over_liggghts_cpu their ratio "
                      "(other jobs on the cores slow the wall clock more)"
                      + ("" if before is None else "; dem_1thread_before: the --before "
                         f"version ({before}) in the same rounds, before this one"))
    for kind in ("3d", "2d"):
        for n in DENSE_NS:
            key = f"{kind}_{n}"
            r = dict(kind=kind, N=n)
            dem_loops, lig_loops, old_loops, dem_cpu, lig_cpu = [], [], [], [], []
            w = None
            for _ in range(DENSE_REPEATS):
                if before is not None:
                    old_loops += run_dense_worker(kind, n, 1, 1, before)["loops"]
                w = run_dense_worker(kind, n, 1, 1)
                dem_loops += w["loops"]
                dem_cpu += w["cpu"]
                if kind == "3d":
                    lig = run_liggghts_dense(P, n, work)
                    if lig is not None:
                        lig_loops.append(lig[0])
                        # the loop's CPU time: the run's less a run of no steps (set-up)
                        lig_cpu.append(lig[2] - run_liggghts_dense(P, n, work, nsteps=0)[2])
            mps = [n * DENSE_STEPS / t / 1e6 for t in dem_loops]
            r["dem_1thread"] = dict(loop_s=dem_loops, mps_median=float(np.median(mps)),
                                    mps_best=max(mps), dt=w["dt"],
                                    contacts_per_particle_end=w["contacts_end"] / n,
                                    neighbour_builds=w["builds"], ke_end=w["ke_end"],
                                    cpu_s=dem_cpu)
            line = f"dense {key}: dem 1 thread {np.median(mps):.2f} M p-steps/s " \
                   f"(best {max(mps):.2f}), {w['contacts_end'] / n:.2f} contacts/particle"
            if old_loops:
                r["dem_1thread_before"] = _before_record(old_loops, dem_loops, n)
                line += f"; before {r['dem_1thread_before']['mps_median']:.2f}"
            if lig_loops:
                lm = [n * DENSE_STEPS / t / 1e6 for t in lig_loops]
                r["liggghts_1proc"] = dict(loop_s=lig_loops, mps_median=float(np.median(lm)),
                                           mps_best=max(lm), source="run here",
                                           cpu_loop_s=lig_cpu)
                r["ratio_dem_over_liggghts"] = float(np.median(mps) / np.median(lm))
                # CPU time: less sensitive to other jobs on the cores than the wall clock
                r["ratio_dem_over_liggghts_cpu"] = float(np.median(lig_cpu) / np.median(dem_cpu))
                line += (f"; LIGGGHTS {np.median(lm):.2f}: ratio {r['ratio_dem_over_liggghts']:.2f}"
                         f" (CPU time {r['ratio_dem_over_liggghts_cpu']:.2f})")
                if n == DENSE_NS[0]:  # the trajectories agree: KE and contacts at the end
                    _, rows, _ = run_liggghts_dense(P, n, work, diag=True)
                    r["liggghts_end"] = dict(step=rows[-1][0], ke=rows[-1][1],
                                             contacts=rows[-1][2])
            elif kind == "3d":
                r["liggghts_1proc"] = dict(source="liggghts binary not found here")
            print(line)
            dense["scenes"][key] = r
    loops, old = [], []
    for _ in range(DENSE_REPEATS):
        if before is not None:
            old += run_dense_worker("idle", IDLE_N, 1, 1, before)["loops"]
        w = run_dense_worker("idle", IDLE_N, 1, 1)
        loops += w["loops"]
    us = [t / DENSE_STEPS * 1e6 for t in loops]
    dense["fixed_cost"] = dict(
        N=w["n"], us_per_step_median=float(np.median(us)), us_per_step_best=min(us),
        loop_s=loops, note="spheres 0.1 mm apart in a closed box, no gravity: "
        "candidates but no contact; one numba thread")
    line = f"fixed cost: {w['n']} spheres without contacts, {np.median(us):.1f} us a step"
    if old:
        uo = [t / DENSE_STEPS * 1e6 for t in old]
        dense["fixed_cost"]["before"] = dict(loop_s=old, us_per_step_median=float(np.median(uo)),
                                             us_per_step_best=min(uo))
        line += f" (before: {np.median(uo):.1f})"
    print(line)
    res["dense"] = dense


def bar_plot(res, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dense = res.get("dense")
    settle = bool(res.get("runs"))
    fig, axes = plt.subplots(1, int(settle) + int(dense is not None), figsize=(13, 4),
                             squeeze=False)
    axes = list(axes[0])
    if dense is not None:
        dense_plot(dense, axes[-1])
    if not settle:
        fig.tight_layout()
        fig.savefig(path, dpi=120)
        return
    ax = axes[0]
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
    ax.set_title("settle scene, 2000 steps: numba dem (threads, MPI ranks) vs LIGGGHTS",
                 fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def dense_plot(dense, ax):
    keys = list(dense["scenes"])
    for k, key in enumerate(keys):
        r = dense["scenes"][key]
        bars = [("dem 1 thread", r["dem_1thread"]["mps_median"], "C0")]
        if "mps_median" in r.get("liggghts_1proc", {}):
            bars.append(("LIGGGHTS 1 proc", r["liggghts_1proc"]["mps_median"], "C1"))
        if "dem_1thread_before" in r:
            bars.insert(0, ("dem 1 thread, --before", r["dem_1thread_before"]["mps_median"],
                            "C7"))
        w = 0.8 / len(bars)
        for b, (lab, val, col) in enumerate(bars):
            off = (b - (len(bars) - 1) / 2) * w
            ax.bar(k + off, val, w, color=col, label=lab if k == 0 else None)
            ax.text(k + off, val, f"{val:.1f}", ha="center", va="bottom", fontsize=7)
    ax.set_xticks(range(len(keys)), [k.replace("_", "\nN = ") for k in keys], fontsize=8)
    ax.set_ylabel("M particle-steps / s (median)")
    ax.set_title(f"dense lattices from rest, {dense['steps']} steps, one core", fontsize=9)
    ax.legend(fontsize=8)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="output/dem_throughput/")
    ap.add_argument("--worker", nargs=3, type=int, help=argparse.SUPPRESS)
    ap.add_argument("--mpi-worker", nargs=2, type=int, help=argparse.SUPPRESS)
    ap.add_argument("--dense-worker", nargs=3, help=argparse.SUPPRESS)
    ap.add_argument("--before", default=None,
                    help="a directory holding another version's dem package: the dense "
                         "scenes run on it too, in the same rounds")
    ap.add_argument("--scenes", default="settle,dense",
                    help="comma-separated: settle (peers' scene, N = 10k, 50k: threads, MPI "
                         "ranks, LIGGGHTS) and/or dense (window-size lattices)")
    args = ap.parse_args()
    if args.worker:
        return worker(*args.worker)
    if args.mpi_worker:
        return mpi_worker(*args.mpi_worker)
    if args.dense_worker:
        kind, n, repeats = args.dense_worker
        return dense_worker(kind, int(n), int(repeats))
    scenes = set(args.scenes.split(","))
    if not scenes <= {"settle", "dense"}:
        ap.error(f"--scenes: unknown {sorted(scenes - {'settle', 'dense'})}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    P = peers_params()
    res = dict(scene="peers settle (tools/params.py settle_params, lattice)", N=NS,
               nsteps=NSTEPS, repeats=REPEATS, params=P.settle_params(), runs={},
               machine=machine_info(), scenes_run=sorted(scenes))
    print(f"machine: {res['machine'].get('cpu_model')}, numba target "
          f"{res['machine']['numba_target_cpu']}")
    if "dense" in scenes:
        with tempfile.TemporaryDirectory() as work:
            run_dense(res, P, work, args.before)
    if "settle" not in scenes:
        res["N"] = []
        return finish(res, out)

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
    finish(res, out)

    # ---------------------------------------------------------------- checks
    for n in NS:
        rn = res["runs"][str(n)]
        c = rn["contacts"]
        c2000 = c[str(NSTEPS)] if str(NSTEPS) in c else c[NSTEPS]
        assert abs(rn["ke_2000_rel_diff"]) < 0.02, "KE(2000) departs from LIGGGHTS by > 2 %"
        assert abs(c2000 / LIGGGHTS_RESULTS[n]["contacts"][2000] - 1) < 0.02


def finish(res, out):
    """Write results.json and the plot."""
    res["load_average_at_end"] = os.getloadavg()
    res["machine_note"] = ("2-vCPU VM shared with other jobs: compare medians and rerun; the "
                           "LIGGGHTS numbers from RESULTS.md were measured on an idle machine")
    (out / "results.json").write_text(json.dumps(res, indent=1, default=str))
    bar_plot(res, out / "throughput.png")
    print(f"wrote {out / 'results.json'} and {out / 'throughput.png'}")


if __name__ == "__main__":
    main()
