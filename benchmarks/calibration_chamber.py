"""The virtual calibration chamber (2D): coupled cone penetration against full DEM of the
whole chamber, error against run time, under a vertical stress and the chambers' standard
boundary conditions.

Chamber (plane strain, per unit thickness): width ``--width-ratio`` x the cone diameter
(20: physical chambers are 17-50 cone diameters across), cone diameter ``--cone-grains`` x
the mean grain diameter (6), a 60 degree cone pushed ``--push`` cone diameters (3) at
``--velocity``; the grains are linear frictional disks (kn 5e7 N/m per m: overlaps of
0.2 % of a diameter at 100 kPa) consolidated under a vertical stress ``--stress`` on the
top row (:mod:`coupling.apps.penetration.chamber`), sides rigid, then pushed with

- BC3: constant vertical stress, zero lateral strain (rigid sides), and
- BC1: constant vertical and lateral stress (the side walls replaced by the forces they
  carried after consolidation: a flexible membrane).

Reference: full DEM of the whole chamber, ``--reference-seeds`` packings (lattice jitter and radii
drawn per seed). Coupled: the same chamber with DE windows of half width ``--windows`` [m]
(the rest a micropolar continuum carrying the increment from the consolidated state: top
traction-free, sides on rollers (BC3) or traction-free (BC1)), the same packings' seeds.
With ``--boxes``, also full DEM of each window with its ghost band alone, inside the
chamber's walls (rigid, smooth): what the window gives when its surround is rigid.
Every case runs in its own process (``--worker``), so its wall times (set-up: building and
consolidating; push) and its peak memory (``ru_maxrss``) are its own. With
``--reference-ranks N`` (3D) the full-DEM reference runs on a `dem.DistributedSimulation` over
N MPI ranks (``mpiexec -n N``, one numba thread each); its record then holds ``ranks``, its
CPU seconds and peak memory summed over the ranks.

Per case: q_c(depth) and f_s(depth) (ISO 22476-1 sleeve, :func:`coupling.apps.penetration.
penetrators.cone_record`), smoothed over ``--smooth``; the error of the seed-averaged q_c
against the seed-averaged full DEM (relative RMS over depth once the cone is embedded, and
the relative difference of the mean over the steady part: the last half of the push); the
reference's own scatter (one packing against the average, and the standard error of the
average). Writes ``<--name>.json`` and ``<--name>.png`` (q_c profiles, error against run time
with the reference's scatter as a band) to ``--results``; ``calibration_chamber`` is the
20-cone-diameter chamber, ``calibration_chamber_w30`` the 30-diameter one (``--width-ratio
30``: where size effects in loose sand fade, and where the full DEM costs 2.3x more while
the coupled run, whose far field is a coarse mesh, costs about the same).

Run: ``python benchmarks/calibration_chamber.py`` (about an hour on 2 idle cores, one core
used at a time: per boundary condition 3 full-DEM packings of about 3 minutes each and 36
coupled runs of 15-40 s); ``GRANFE_SHORT=1`` a few-minute version on a smaller chamber.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from machine import machine

SHORT = os.environ.get("GRANFE_SHORT") == "1"
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--results", type=Path, default=Path("benchmarks/results"))
parser.add_argument("--work", type=Path, default=Path("output/calibration_chamber"))
parser.add_argument("--grain-radius", type=float, default=1.5e-3, help="mean grain radius [m]")
parser.add_argument("--dim", type=int, default=2, choices=[2, 3],
                    help="2: plane-strain disks; 3: Hertz-Mindlin spheres in a square chamber under a "
                         "servo-controlled top plate (BC3 only)")
parser.add_argument("--cone-grains", type=float, default=None, help="cone diameter / grain diameter (2D 6, 3D 4)")
parser.add_argument("--width-ratio", type=float, default=8.0 if SHORT else 20.0,
                    help="chamber width / cone diameter")
parser.add_argument("--depth-ratio", type=float, default=None, help="chamber depth / chamber width (2D 0.8, 3D "
                    "0.35: the 3D window's base 2 cone diameters below the final tip, 1.5 above the chamber's)")
parser.add_argument("--push", type=float, default=1.5 if SHORT else 3.0, help="push [cone diameters]")
parser.add_argument("--stress", type=float, default=1e5, help="vertical stress on top [Pa]")
parser.add_argument("--velocity", type=float, default=1.0, help="push velocity [m/s]")
parser.add_argument("--windows", type=float, nargs="+", default=None,
                    help="DE window half widths [m] (2D 0.045 0.06 0.075, 3D 0.02 0.025)")
parser.add_argument("--bcs", nargs="+", default=None, help="BC3 and/or BC1 (2D; 3D: BC3)")
parser.add_argument("--seeds", type=int, default=2 if SHORT else 3, help="packings of each coupled case")
parser.add_argument("--first-seed", type=int, default=1,
                    help="the coupled cases' first packing (seeds first .. first + seeds - 1): packings not "
                         "used to choose a setting (the reference always takes seeds 1 ..)")
parser.add_argument("--reference-seeds", type=int, default=None,
                    help="packings of the full-DEM reference (default --seeds)")
parser.add_argument("--smooth", type=float, default=0.006, help="depth window of the q_c filter [m]")
parser.add_argument("--interface", default="loose", choices=["loose", "iqn-ils", "forces"],
                    help="the coupled cases' exchange (coupling.interface)")
parser.add_argument("--relaxation", type=float, default=0.1,
                    help="coupling.relaxation (0.3 diverged in a short chamber at 1.3 cone diameters)")
parser.add_argument("--substeps", type=int, default=50,
                    help="the coupled cases' DEM steps per FE step (coupling.substeps): the loose "
                         "exchange's prescribed displacements trail the grains by about "
                         "substeps / relaxation DEM steps")
parser.add_argument("--handshake", type=float, default=2.0,
                    help="the coupled cases' free FE layer inside the window [elements] "
                         "(window.handshake): the FE nodes deeper inside are prescribed from the grains")
parser.add_argument("--continuum", nargs="+", default=None,
                    choices=["micropolar", "micropolar_drucker_prager"],
                    help="the coupled cases' continuum models (each with every window)")
parser.add_argument("--constants", nargs="+", default=None,
                    choices=["lattice", "calibrated", "window", "window_isotropic"],
                    help="where the coupled cases' continuum constants come from (each with every "
                         "model and window): the lattice estimate, element tests on a periodic "
                         "cell of the grains at the window's stress (with the plastic model also "
                         "its friction and dilatancy angles), or (3D) the lattice estimate scaled to "
                         "the window's constrained modulus probed in situ (window_isotropic: both "
                         "isotropic constants from that probe)")
parser.add_argument("--hardening", type=float, nargs="+", default=[0.0],
                    help="the Drucker-Prager cases' hardening of the cohesion [Pa per unit equivalent plastic "
                         "strain], each with every plastic case (0: perfectly plastic; a window driven by its "
                         "grains then drifts once the continuum round it yields)")
parser.add_argument("--integrator", choices=("implicit", "explicit"), default="implicit",
                    help="the coupled cases' continuum time stepping (continuum.integrator): generalized-"
                         "alpha, or central differences on a lumped mass substepped below the stability "
                         "limit (granfe.explicit: a plastic step without a solve)")
parser.add_argument("--damping", type=float, default=0.0,
                    help="the explicit continuum's mass-proportional damping [1/s] (continuum.damping)")
parser.add_argument("--stiffness", type=float, default=1.0,
                    help="coupling continuum_stiffness: the continuum's constants times this (the coupled cases)")
parser.add_argument("--friction-deg", type=float, default=30.0,
                    help="the Drucker-Prager continuum's friction angle (plane-strain match)")
parser.add_argument("--boxes", action="store_true",
                    help="also run full DEM in a rigid smooth box the size of each window with its "
                         "ghost band (the chamber's boundary condition on its sides): what a window "
                         "gives when its surround is rigid, beside what the continuum gives")
parser.add_argument("--liggghts", type=int, default=0,
                    help="3D: also run the reference's first N packings in LIGGGHTS (benchmarks/liggghts_chamber.py: "
                         "the same packing, law and loading), one core each, timed in this invocation")
parser.add_argument("--reference-ranks", type=int, default=1,
                    help="3D: MPI ranks of each full-DEM reference packing (mpiexec -n N beside this "
                         "script's Python; a dem.DistributedSimulation, one numba thread a rank)")
parser.add_argument("--reuse", action="store_true",
                    help="take a case's record from --work if it ran with the same parameters")
parser.add_argument("--reference", type=Path, default=None,
                    help="take the full-DEM runs from an earlier results file (its chamber must be "
                         "this one; their wall times are then from that run, not this one)")
parser.add_argument("--merge", type=Path, nargs="+", default=None,
                    help="combine the boundary conditions of these results files (runs split over "
                         "processes: --bcs BC3 in one, --bcs BC1 in another) into one, with its figure")
parser.add_argument("--name", default=None,
                    help="stem of the results file and figure in --results (e.g. one per chamber size)")
parser.add_argument("--worker", type=Path, default=None, help=argparse.SUPPRESS)
args = parser.parse_args()
# the defaults that depend on the dimension (3D: a short window list, the elastic continuum
# with its affine constants; the 3D plastic continuum's Newton solves are not yet affordable)
for key, two, three in (("cone_grains", 6.0, 4.0), ("depth_ratio", 0.8, 0.35),
                        ("windows", [0.03] if SHORT else [0.045, 0.06, 0.075], [0.02, 0.025]),
                        ("bcs", ["BC3"] if SHORT else ["BC3", "BC1"], ["BC3"]),
                        ("continuum", ["micropolar"] if SHORT else ["micropolar", "micropolar_drucker_prager"],
                         ["micropolar"]),
                        ("constants", ["lattice"] if SHORT else ["lattice", "calibrated"], ["lattice"]),
                        ("name", "calibration_chamber_short" if SHORT else "calibration_chamber",
                         "calibration_chamber_3d_short" if SHORT else "calibration_chamber_3d")):
    if getattr(args, key) is None:
        setattr(args, key, two if args.dim == 2 else three)

if args.first_seed < 1 or args.seeds < 1:
    parser.error(f"--first-seed {args.first_seed}, --seeds {args.seeds}: both >= 1")
if args.reference_ranks < 1 or (args.reference_ranks > 1 and args.dim != 3):
    parser.error(f"--reference-ranks {args.reference_ranks}: >= 1, and above 1 only with --dim 3 "
                 f"(the full DEM distributed is the 3D chamber's)")
LATERAL = {"BC3": "rigid", "BC1": "stress"}


def parameters(bc: str, seed: int, window: float | None, continuum: str = "micropolar",
               constants: str = "lattice", hardening: float = 0.0) -> dict:
    """The PenetrationParameters of one case (window None: the full DEM's, whose window
    fields only size its unused continuum checks)."""
    r = args.grain_radius
    cone_radius = args.cone_grains * r
    width = args.width_ratio * 2 * cone_radius
    depth = args.push * 2 * cone_radius
    # the window's bottom lies as far below the final tip as its side lies beside the cone's
    # shoulder (at least two cone radii and six grain diameters)
    window_depth = depth + max(2 * cone_radius + 12 * r, (window or 0.0) - cone_radius)
    # 2D: linear disks at three times the engine's default step (0.15 of the critical one);
    # 3D: Hertz spheres (E = 29 MPa) at the default 0.2 of the Rayleigh step (deeper contacts
    # under the plate heat the packing at 0.3, coupling.apps.penetration.chamber)
    grains = dict(kn=5e7, dt_factor=3.0) if args.dim == 2 else dict(dim=3, dt_factor=1.0)
    return dict(chamber_width=width, chamber_depth=args.depth_ratio * width, radius=r, cone_radius=cone_radius,
                velocity=args.velocity, depth=depth, vertical_stress=args.stress,
                lateral=LATERAL[bc], consolidation_tol=1e-2, seed=seed,
                window_half_width=window or (0.03 if args.dim == 2 else 0.02), window_depth=window_depth,
                element_size_window=(2.5 if args.dim == 2 else 2.0) * 2 * r, element_size_far=width / 8) | grains | (
                    {} if continuum == "micropolar" else
                    dict(continuum=continuum, continuum_friction_deg=args.friction_deg)) | (
                    {} if constants == "lattice" else dict(continuum_constants=constants)) | (
                    dict(continuum_hardening=hardening) if hardening else {}) | (
                    dict(continuum_stiffness=args.stiffness) if window and args.stiffness != 1.0 else {}) | (
                    dict(continuum_integrator=args.integrator) if window and args.integrator != "implicit" else {}) | (
                    dict(continuum_damping=args.damping) if window and args.damping else {}) | {
                    # the handshake named only off its default (the records before it had none)
                    k: v for k, v in exchange(window).items() if k != "handshake" or v != parser.get_default(k)}


# the coupled cases' exchange settings, and how a record's name marks one off its default
EXCHANGE_TAGS = {"interface": {"iqn-ils": "_iqn", "forces": "_forces"}.get, "relaxation": "_rel{:g}".format,
                 "substeps": "_sub{}".format, "handshake": "_hs{:g}".format}


def exchange(window: float | None) -> dict:
    """The exchange settings of a case: the command line's for a coupled case, the defaults for
    the full DEM (which has no exchange: its record serves every choice)."""
    return {k: getattr(args, k) if window else parser.get_default(k) for k in EXCHANGE_TAGS}


def box_parameters(bc: str, seed: int, window: float) -> dict:
    """Full DEM of the window with its ghost band only, inside the chamber's walls (rigid
    and smooth): the chamber cut down to the coupled case's grains."""
    from coupling.apps.penetration.parameters import PenetrationParameters

    band = PenetrationParameters.ghost_width * 2 * args.grain_radius
    # the window fields only size the full DEM's unused continuum checks (as for the chamber)
    return parameters(bc, seed, None) | dict(chamber_width=2 * (window + band),
                                             chamber_depth=parameters(bc, seed, window)["window_depth"] + band)


def worker(path: Path) -> None:
    """One case, from the JSON at ``path``; writes its record beside it."""
    from dataclasses import replace

    import dolfinx_solver  # noqa: F401
    from mpi4py import MPI

    from coupling.apps.penetration.coupled import (
        CoupledPenetration,
        CouplingUnstable,
        DemPenetration,
        PenetrationParameters,
    )

    case = json.loads(path.read_text())
    prm = PenetrationParameters(**case["parameters"])
    comm = MPI.COMM_WORLD
    t0, c0 = time.perf_counter(), time.process_time()
    if case["window"] is None:
        # every rank of an mpiexec launch (``ranks`` in the case) runs the distributed model
        model = DemPenetration(prm, log=lambda m: None, comm=comm if case.get("ranks", 1) > 1 else None)
    else:
        model = CoupledPenetration(prm, MPI.COMM_WORLD, log=lambda m: None)
    t1, c1 = time.perf_counter(), time.process_time()
    failed = None
    try:
        history = model.run()
    except CouplingUnstable as err:
        # the loose exchange diverged: the case is run again, iterated (IQN-ILS), and both
        # times count (a user would have paid them)
        failed = {"depth": model.depth, "message": str(err), "wall_time": time.perf_counter() - t1}
        prm = replace(prm, interface="iqn-ils")
        model = CoupledPenetration(prm, MPI.COMM_WORLD, log=lambda m: None)
        try:
            history = model.run()
        except CouplingUnstable as err:
            # both exchanges diverged: the packing is recorded as stopped, with its profile
            # up to there (it counts in no error)
            failed["iterated"] = {"depth": model.depth, "message": str(err)}
            history = model.history
    t2, c2 = time.perf_counter(), time.process_time()
    # CPU seconds beside the wall times: a neighbour on a shared core stretches the wall
    # time, far less the CPU time (over all ranks of a distributed reference, as its memory)
    cpu = comm.allreduce(np.array([c1 - c0, c2 - c1]))
    memory = comm.allreduce(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    if comm.rank != 0:
        return
    out = {"grains": int(model.n_grains), "setup_s": t1 - t0, "push_s": t2 - t1,
           "setup_cpu_s": float(cpu[0]), "push_cpu_s": float(cpu[1]),
           "interface": prm.interface, "loose_exchange_failed": failed,
           "stopped": bool(failed and "iterated" in failed),
           "peak_memory_mb": memory,
           "dem_steps": int(model.sim.nsteps), "dt": float(model.sim.dt),
           "depth": [h["depth"] for h in history], "q_c": [h["q_c"] for h in history],
           "f_s": [h["f_s"] for h in history]}
    if case["window"] is not None:
        V = model.problem.V
        out["dofs"] = int(V.dofmap.index_map.size_global * V.dofmap.index_map_bs)
        out["split_s"] = {k: float(np.sum([t.get(k, 0.0) for t in model.step_timings]))
                          for k in model.step_timings[0]}
        out["calibration"] = model.contact_stats.get("calibration")
        out["window_modulus"] = model.contact_stats.get("window_modulus")
        state = model.problem.state
        if state and "equivalent_plastic_strain" in state.committed:
            # how much of the continuum yielded by the end (quadrature points of this rank)
            eq = state.owned("equivalent_plastic_strain")
            out["plastic"] = {"yielded_fraction": float(np.mean(eq > 0)),
                              "fraction_above_1e-3": float(np.mean(eq > 1e-3)),
                              "max_equivalent_plastic_strain": float(eq.max())}
    if case.get("ranks", 1) > 1:
        out["ranks"] = comm.size
    path.with_suffix(".out.json").write_text(json.dumps(out))


def reused(path: Path, case: dict) -> dict | None:
    """With ``--reuse``, the record of the case at ``path`` if it ran with these parameters."""
    done = path.with_suffix(".out.json")
    if args.reuse and done.exists() and path.exists() and json.loads(path.read_text()) == case:
        print(f"{path.stem}: reused from {done}", flush=True)
        return json.loads(done.read_text())
    return None


def run_case(bc: str, seed: int, window: float | None, continuum: str = "micropolar",
             constants: str = "lattice", box: float | None = None, hardening: float = 0.0) -> dict:
    """One packing of one case in its own process: full DEM of the chamber (window None),
    full DEM of a rigid box the size of window ``box``, or the coupled chamber."""
    tag = ("" if continuum == "micropolar" else "_dp") + CONSTANTS_TAGS[constants] + (
        f"_h{hardening:g}" if hardening else "") + (
        f"_k{args.stiffness:g}" if window and args.stiffness != 1.0 else "") + (
        "_explicit" if window and args.integrator != "implicit" else "") + (
        f"_damp{args.damping:g}" if window and args.damping else "") + "".join(
        EXCHANGE_TAGS[k](v) for k, v in exchange(window).items() if v != parser.get_default(k))
    if box is not None:
        name = f"{bc}_box{box * 1000:.0f}mm_s{seed}"
        case = {"parameters": box_parameters(bc, seed, box), "window": None}
    else:
        name = f"{bc}_{'full' if window is None else f'w{window * 1000:.0f}mm{tag}'}_s{seed}"
        case = {"parameters": parameters(bc, seed, window, continuum, constants, hardening), "window": window}
    launch = [sys.executable, __file__, "--worker"]
    if window is None and box is None and args.reference_ranks > 1:
        # the reference distributed (named apart: a record of another rank count is not reused)
        name, case["ranks"] = f"{name}_n{args.reference_ranks}", args.reference_ranks
        launch = [str(Path(sys.executable).parent / "mpiexec"), "-n", str(args.reference_ranks)] + launch
    path = args.work / f"{name}.json"
    old = reused(path, case)
    if old is not None:
        return old
    path.write_text(json.dumps(case))
    proc = subprocess.run(launch + [str(path)], capture_output=True, text=True,
                          env={**os.environ, "NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"})
    if proc.returncode:
        raise RuntimeError(f"case {name} failed:\n{proc.stderr[-3000:]}")
    out = json.loads(path.with_suffix(".out.json").read_text())
    ranks = f" on {out['ranks']} ranks" if "ranks" in out else ""
    cpu = out.get("setup_cpu_s", np.nan) + out.get("push_cpu_s", np.nan)
    print(f"{name}: {out['grains']} grains{ranks}, set-up {out['setup_s']:.1f} s, push {out['push_s']:.1f} s "
          f"(CPU {cpu:.1f} s), peak {out['peak_memory_mb']:.0f} MB, mean q_c (last half) "
          f"{np.mean(out['q_c'][len(out['q_c']) // 2:]) / 1e3:.1f} kPa", flush=True)
    return out


def run_peer(bc: str, seed: int) -> dict:
    """The full-DEM chamber of packing ``seed`` in LIGGGHTS (one core), reused like a case."""
    from liggghts_chamber import run_case as run_liggghts

    prm = parameters(bc, seed, None)
    name = f"{bc}_liggghts_s{seed}"
    path = args.work / f"{name}.json"
    old = reused(path, {"parameters": prm})
    if old is not None:
        return old
    path.write_text(json.dumps({"parameters": prm}))
    out = run_liggghts(prm, args.work / name, cores=1)
    path.with_suffix(".out.json").write_text(json.dumps(out))
    print(f"{name}: {out['grains']} grains, set-up {out['setup_s']:.1f} s, push {out['push_s']:.1f} s", flush=True)
    return out


def smoothed(run: dict, key: str, grid: np.ndarray) -> np.ndarray:
    from coupling.apps.penetration.penetrators import filtered

    hist = [{"depth": d, key: v} for d, v in zip(run["depth"], run[key], strict=True)]
    return np.interp(grid, run["depth"], filtered(hist, key, args.smooth))


def seed_reference(bc: str, seeds: list[int]) -> None:
    """Put the full-DEM runs of ``args.reference`` into the work directory as finished cases
    (``--reuse`` then takes them), after checking that its chamber is this one."""
    old = json.loads(args.reference.read_text())["cases"].get(bc)
    if old is None or old["parameters"] != parameters(bc, 1, None):
        raise SystemExit(f"--reference {args.reference}: no {bc} case with this chamber's parameters")
    runs = old["full_dem"]["runs"]
    if len(runs) < len(seeds):
        raise SystemExit(f"--reference {args.reference}: {len(runs)} {bc} packings, {len(seeds)} asked")
    for s, run in zip(seeds, runs, strict=False):
        case = {"parameters": parameters(bc, s, None), "window": None}
        path = args.work / f"{bc}_full_s{s}.json"
        if args.reference_ranks > 1:  # named and recorded as run_case names a distributed reference
            path, case["ranks"] = args.work / f"{bc}_full_s{s}_n{args.reference_ranks}.json", args.reference_ranks
        path.write_text(json.dumps(case))
        path.with_suffix(".out.json").write_text(json.dumps(run))
    args.reuse = True


CONSTANTS_TAGS = {"lattice": "", "calibrated": "_cal", "window": "_win", "window_isotropic": "_wiso"}


def case_label(case: dict) -> str:
    """The continuum and exchange of a coupled case's summary (records before these fields
    had the defaults)."""
    label = f"{case.get('continuum', 'micropolar')}, {case.get('constants', 'lattice')} constants"
    if case.get("hardening"):
        label += f", H {case['hardening'] / 1e6:g} MPa"
    if case.get("stiffness", 1.0) != 1.0:
        label += f", stiffness x{case['stiffness']:g}"
    if case.get("integrator", "implicit") != "implicit":
        label += f", {case['integrator']} continuum"
    if case.get("damping"):
        label += f" (damping {case['damping']:g}/s)"
    if case.get("exchange", {}).get("interface", "loose") != "loose":
        label += f", {case['exchange']['interface']} exchange"
    return label


def cpu_total(runs: list[dict]) -> float | None:
    """Mean CPU seconds (set-up + push) of runs that recorded them (None if any did not)."""
    if not all("push_cpu_s" in r for r in runs):
        return None
    return float(np.mean([r["setup_cpu_s"] + r["push_cpu_s"] for r in runs]))


def comparison_noise(reference: dict, q_runs: list, embedded, scale: float, n_ref: int) -> float | None:
    """sqrt(s_ref^2 / N_ref + s_case^2 / N_case) [relative]: the expected RMS difference of
    the two averages if the case had no bias (s: packing scatters, sample variances)."""
    if len(q_runs) < 2:
        return None
    s_case = np.sqrt(np.mean(np.array(q_runs)[:, embedded].var(axis=0, ddof=1))) / scale
    return float(np.sqrt(reference["packing_scatter"] ** 2 / n_ref + s_case**2 / len(q_runs)))


def compare(bc: str) -> dict:
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    ref_seeds = list(range(1, (args.reference_seeds or args.seeds) + 1))
    if args.reference is not None:
        seed_reference(bc, ref_seeds)
    full = [run_case(bc, s, None) for s in ref_seeds]
    grid = np.array(full[0]["depth"])
    prm = parameters(bc, 1, None)
    # compare once the cone tip is a third of its height into the grains
    embedded = grid > prm["cone_radius"] / np.tan(np.radians(30.0)) / 3
    tail = grid >= grid[-1] / 2
    q_full = np.array([smoothed(r, "q_c", grid) for r in full])
    q_ref = q_full.mean(axis=0)
    scale = np.sqrt(np.mean(q_ref[embedded] ** 2))

    def rms(q):
        return float(np.sqrt(np.mean((q[embedded] - q_ref[embedded]) ** 2)) / scale)

    def tail_mean(runs):
        return float(np.mean([np.mean(np.interp(grid, r["depth"], r["q_c"])[tail]) for r in runs]))

    ref_tail = tail_mean(full)
    reference = {
        "grains": full[0]["grains"], "setup_s": [r["setup_s"] for r in full], "push_s": [r["push_s"] for r in full],
        "total_s_mean": float(np.mean([r["setup_s"] + r["push_s"] for r in full])),
        "push_s_mean": float(np.mean([r["push_s"] for r in full])),
        "total_cpu_s_mean": cpu_total(full),
        "peak_memory_mb": max(r["peak_memory_mb"] for r in full),
        "q_c_mean": q_ref.tolist(), "q_c_std": q_full.std(axis=0).tolist(),
        "f_s_mean": np.mean([smoothed(r, "f_s", grid) for r in full], axis=0).tolist(),
        "q_c_steady_mean": ref_tail,
        "one_packing_rms_vs_average": float(np.mean([rms(q) for q in q_full])),
        # each packing against the average of the others: what one more packing of the
        # reference would be off by (the average above includes the packing itself, which
        # pulls it closer by sqrt((N - 1) / N))
        "one_packing_rms_vs_others": float(np.mean([
            np.sqrt(np.mean((q[embedded] - np.delete(q_full, k, axis=0).mean(axis=0)[embedded]) ** 2)) / scale
            for k, q in enumerate(q_full)])) if len(full) > 1 else None,
        "one_packing_steady_vs_average": float(np.mean([abs(tail_mean([r]) - ref_tail) / abs(ref_tail)
                                                         for r in full])),
        "standard_error_of_average": float(np.sqrt(np.mean(q_full[:, embedded].var(axis=0, ddof=1))
                                                   / len(ref_seeds)) / scale),
        # a packing's scatter about the sand's mean (sample variance, ddof 1): the
        # one-packing RMS above is this x sqrt((N - 1) / N)
        "packing_scatter": float(np.sqrt(np.mean(q_full[:, embedded].var(axis=0, ddof=1))) / scale),
        "runs": full}
    print(f"{bc} full DEM: {reference['grains']} grains, one packing against the average "
          f"{reference['one_packing_rms_vs_average']:.1%} RMS, standard error of the average "
          f"{reference['standard_error_of_average']:.1%}", flush=True)
    peer = None
    if args.liggghts:
        # the tool a user would pick instead: the same chamber's packings in LIGGGHTS; its
        # q_c against our reference's average says how close the two codes' physics are
        # (the cone a mesh there, a clump of spheres here)
        peer_runs = [run_peer(bc, s) for s in ref_seeds[:args.liggghts]]
        q_peer = np.array([smoothed(r, "q_c", grid) for r in peer_runs])
        peer = {"grains": peer_runs[0]["grains"], "liggghts_version": peer_runs[0].get("liggghts_version"),
                "total_s_mean": float(np.mean([r["setup_s"] + r["push_s"] for r in peer_runs])),
                "push_s_mean": float(np.mean([r["push_s"] for r in peer_runs])),
                "total_cpu_s_mean": cpu_total(peer_runs),
                "granfe_full_dem_over_liggghts": reference["total_s_mean"]
                / float(np.mean([r["setup_s"] + r["push_s"] for r in peer_runs])),
                "q_c_mean": q_peer.mean(axis=0).tolist(),
                "q_c_rms_vs_reference": rms(q_peer.mean(axis=0)),
                "q_c_steady_vs_reference": (tail_mean(peer_runs) - ref_tail) / abs(ref_tail),
                "runs": peer_runs}
        print(f"{bc} LIGGGHTS: {peer['grains']} grains, {peer['total_s_mean']:.0f} s a packing (ours "
              f"{reference['total_s_mean']:.0f} s), q_c {peer['q_c_rms_vs_reference']:.1%} RMS off our "
              "reference", flush=True)
    cases = []
    for constants, continuum, hardening, window in [
            (k, c, h, w) for k in args.constants for c in args.continuum
            for h in (args.hardening if c != "micropolar" else [0.0]) for w in args.windows]:
        tried = [run_case(bc, s, window, continuum, constants, hardening=hardening) for s in seeds]
        name = f"{continuum}{f' (hardening {hardening / 1e6:g} MPa)' if hardening else ''}"
        runs = [r for r in tried if not r.get("stopped")]
        if not runs:
            cases.append({"window_half_width": window, "continuum": continuum, "constants": constants,
                          "hardening": hardening, "stopped_packings": len(tried), "runs": tried})
            print(f"{bc} window {window * 100:.1f} cm, {name}, {constants} constants: every "
                  "packing stopped (both exchanges diverged)", flush=True)
            continue
        q = np.mean([smoothed(r, "q_c", grid) for r in runs], axis=0)
        total = float(np.mean([r["setup_s"] + r["push_s"] for r in runs]))
        push = float(np.mean([r["push_s"] for r in runs]))
        cpu = cpu_total(runs)
        case = {"window_half_width": window, "continuum": continuum, "constants": constants,
                "hardening": hardening, "stiffness": args.stiffness, "integrator": args.integrator,
                "damping": args.damping,
                "exchange": exchange(window),
                "grains": runs[0]["grains"],
                "dofs": runs[0]["dofs"],
                "setup_s": [r["setup_s"] for r in runs], "push_s": [r["push_s"] for r in runs],
                "total_s_mean": total, "push_s_mean": push,
                "peak_memory_mb": max(r["peak_memory_mb"] for r in runs),
                "speedup_total": reference["total_s_mean"] / total,
                "speedup_push": reference["push_s_mean"] / push,
                "total_cpu_s_mean": cpu,
                "speedup_total_cpu": (reference["total_cpu_s_mean"] / cpu
                                      if reference["total_cpu_s_mean"] and cpu else None),
                "speedup_vs_liggghts": peer["total_s_mean"] / total if peer else None,
                "q_c_rms_error": rms(q),
                "q_c_steady_error": abs(tail_mean(runs) - ref_tail) / abs(ref_tail),
                "q_c_rms_error_per_packing": [rms(smoothed(r, "q_c", grid)) for r in runs],
                # what the error of two averages is from packing scatter alone (the
                # reference's and this case's, each over its packings), no bias
                "comparison_noise": comparison_noise(reference, [smoothed(r, "q_c", grid) for r in runs],
                                                     embedded, scale, len(full)),
                "q_c_mean": q.tolist(),
                "f_s_mean": np.mean([smoothed(r, "f_s", grid) for r in runs], axis=0).tolist(),
                # a loose run re-run iterated has other phases (interface_iterations): a phase
                # a run did not have counts 0 in it
                "split_s_mean": {k: float(np.mean([r["split_s"].get(k, 0.0) for r in runs]))
                                 for k in dict.fromkeys(k for r in runs for k in r["split_s"])},
                "calibration": runs[0].get("calibration"),
                "stopped_packings": len(tried) - len(runs),
                "runs": tried}
        case["within_reference_scatter"] = case["q_c_rms_error"] <= reference["one_packing_rms_vs_average"]
        cases.append(case)
        print(f"{bc} window {window * 100:.1f} cm, {case_label(case)}: {case['grains']} grains, "
              f"{case['speedup_total']:.1f}x faster "
              f"(push {case['speedup_push']:.1f}x), q_c RMS error {case['q_c_rms_error']:.1%} (reference scatter "
              f"{reference['one_packing_rms_vs_average']:.1%}), steady mean {case['q_c_steady_error']:.1%}", flush=True)
    boxes = []
    for window in (args.windows if args.boxes else []):
        runs = [run_case(bc, s, None, box=window) for s in seeds]
        q = np.mean([smoothed(r, "q_c", grid) for r in runs], axis=0)
        total = float(np.mean([r["setup_s"] + r["push_s"] for r in runs]))
        box = {"window_half_width": window, "grains": runs[0]["grains"],
               "setup_s": [r["setup_s"] for r in runs], "push_s": [r["push_s"] for r in runs],
               "total_s_mean": total, "speedup_total": reference["total_s_mean"] / total,
               "q_c_rms_error": rms(q), "q_c_bias": float(np.mean(q[embedded] - q_ref[embedded]) / scale),
               "q_c_steady_error": abs(tail_mean(runs) - ref_tail) / abs(ref_tail),
               "q_c_rms_error_per_packing": [rms(smoothed(r, "q_c", grid)) for r in runs],
               "q_c_mean": q.tolist(), "runs": runs}
        boxes.append(box)
        print(f"{bc} rigid box of the window {window * 100:.1f} cm: {box['grains']} grains, q_c RMS error "
              f"{box['q_c_rms_error']:.1%} (mean {box['q_c_bias']:+.1%})", flush=True)
    for c in cases:
        if "q_c_mean" in c:
            c["q_c_bias"] = float(np.mean(np.array(c["q_c_mean"])[embedded] - q_ref[embedded]) / scale)
    return {"parameters": prm, "depth": grid.tolist(), "full_dem": reference, "coupled": cases,
            "rigid_boxes": boxes, "liggghts": peer}


def plot(results: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    bcs = list(results["cases"])
    fig, axes = plt.subplots(1, len(bcs) + 1, figsize=(5.2 * (len(bcs) + 1) + 3.5, 4.8), squeeze=False)
    axes = axes[0]
    for ax, bc in zip(axes, bcs, strict=False):
        r = results["cases"][bc]
        d = np.array(r["depth"]) * 100
        ref, std = np.array(r["full_dem"]["q_c_mean"]) / 1e3, np.array(r["full_dem"]["q_c_std"]) / 1e3
        ax.fill_betweenx(d, ref - std, ref + std, color="0.85", label="full DEM, +-1 std over packings")
        ax.plot(ref, d, "k", lw=2, label=f"full DEM ({r['full_dem']['grains']} grains)")
        # the profiles of the best setting at each window (every setting is in the error panel)
        best = {}
        for c in (c for c in r["coupled"] if "q_c_mean" in c):
            w = c["window_half_width"]
            if w not in best or c["q_c_rms_error"] < best[w]["q_c_rms_error"]:
                best[w] = c
        for c in (best[w] for w in sorted(best)):
            plastic = c.get("continuum", "micropolar") != "micropolar"
            calibrated = c.get("constants", "lattice") == "calibrated"
            ax.plot(np.array(c["q_c_mean"]) / 1e3, d, ls="--" if plastic else "-", lw=2 if calibrated else 1,
                    label=f"coupled ({case_label(c)}), window "
                          f"{c['window_half_width'] * 100:.1f} cm ({c['grains']} grains)")
        if r.get("liggghts"):
            ax.plot(np.array(r["liggghts"]["q_c_mean"]) / 1e3, d, color="C3", lw=1.5,
                    label=f"LIGGGHTS, the same packings ({len(r['liggghts']['runs'])})")
        for b in r.get("rigid_boxes", []):
            ax.plot(np.array(b["q_c_mean"]) / 1e3, d, ":", lw=1.5,
                    label=f"full DEM in a rigid box of the {b['window_half_width'] * 100:.1f} cm window "
                          f"({b['grains']} grains)")
        ax.invert_yaxis()
        ax.set_xlabel(f"q_c, filtered over {args.smooth * 1000:.0f} mm [kPa]")
        ax.set_ylabel("depth [cm]")
        ax.set_title(f"{bc}, sigma_v = {args.stress / 1e3:.0f} kPa, {len(r['full_dem']['runs'])} packings")
        ax.legend(fontsize=6, loc="lower left")   # the profiles keep to the upper left and the right
    ax = axes[-1]
    for k, bc in enumerate(bcs):
        r = results["cases"][bc]
        ref = r["full_dem"]
        color = f"C{k}"
        ax.axhspan(0, ref["one_packing_rms_vs_average"], color=color, alpha=0.12,
                   label=f"{bc}: one full-DEM packing vs average")
        groups = sorted({case_label(c) for c in r["coupled"]})
        for label, marker in zip(groups, "os^DvP*h", strict=False):
            pts = [c for c in r["coupled"] if "q_c_rms_error" in c and case_label(c) == label]
            constants = pts[0].get("constants", "lattice") if pts else "lattice"
            if pts:
                # markers only: run times measured on shared cores are noisier than the
                # windows' order, so a line through them would zigzag
                ax.plot([c["total_s_mean"] for c in pts], [c["q_c_rms_error"] for c in pts], marker, color=color,
                        mfc="none" if constants == "lattice" else color,
                        label=f"{bc}: coupled, {label} (seed-averaged)")
                for c in pts:
                    ax.annotate(f"{c['window_half_width'] * 100:g}", (c["total_s_mean"], c["q_c_rms_error"]),
                                fontsize=6, xytext=(3, 3), textcoords="offset points")
        boxes = r.get("rigid_boxes", [])
        if boxes:
            ax.plot([b["total_s_mean"] for b in boxes], [b["q_c_rms_error"] for b in boxes], "x", color=color,
                    ms=8, label=f"{bc}: full DEM in a rigid box of the window")
            for b in boxes:
                ax.annotate(f"{b['window_half_width'] * 100:g}", (b["total_s_mean"], b["q_c_rms_error"]),
                            fontsize=6, xytext=(3, -8), textcoords="offset points")
        ax.axvline(ref["total_s_mean"], color=color, ls="--", label=f"{bc}: full DEM run time")
        if r.get("liggghts"):
            ax.axvline(r["liggghts"]["total_s_mean"], color="C3", ls=":", label=f"{bc}: LIGGGHTS run time")
    ax.set_xscale("log")
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())   # (they overlapped)
    ax.set_xlabel("run time per packing [s] (set-up + push, wall; a coupled case on one core, the reference "
                  "on its ranks)")
    ax.set_ylabel("relative RMS error of q_c against the full-DEM average")
    worst = max([c["q_c_rms_error"] for r in results["cases"].values() for c in r["coupled"]
                 if "q_c_rms_error" in c] + [0.0])
    if worst > 1.0:   # a few settings off by 2-4x would flatten the rest
        ax.set_ylim(0.0, 1.0)
        ax.text(0.99, 0.99, "points above 1 are off the scale", transform=ax.transAxes, ha="right", va="top",
                fontsize=7)
    ax.legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    ax.set_title("error against run time (labels: window half width [cm])", loc="left")
    fig.tight_layout()
    fig.savefig(args.results / f"{args.name}.png", dpi=120)


if __name__ == "__main__":
    if args.worker is not None:
        worker(args.worker)
        sys.exit(0)
    args.results.mkdir(parents=True, exist_ok=True)
    if args.merge:
        parts = [json.loads(f.read_text()) for f in args.merge]
        cases = {}

        def key(x):
            return (case_label(x), x["window_half_width"])

        for part in parts:
            # a later file's reference replaces an earlier one's; coupled cases are joined, a
            # later file's replacing an earlier one's of the same window, model and constants
            for bc, c in part["cases"].items():
                old = {key(x): x for x in cases.get(bc, {}).get("coupled", [])}
                old.update({key(x): x for x in c["coupled"]})
                boxes = {x["window_half_width"]: x for x in cases.get(bc, {}).get("rigid_boxes", [])}
                boxes.update({x["window_half_width"]: x for x in c.get("rigid_boxes", [])})
                cases[bc] = dict(c, coupled=sorted(old.values(), key=key),
                                 rigid_boxes=[boxes[w] for w in sorted(boxes)])
        results = dict(parts[0], cases=cases,
                       merged_from=[{"file": str(f), "command": part["command"], "machine": part["machine"],
                                     "wall_time_s": part["wall_time_s"]} for f, part in zip(args.merge, parts,
                                                                                            strict=True)])
        args.smooth, args.stress = results["inputs"]["smooth"], results["inputs"]["stress"]
        (args.results / f"{args.name}.json").write_text(json.dumps(results, indent=1, default=float))
        plot(results)
        print(f"wrote {args.results / args.name}.json")
        sys.exit(0)
    args.work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    results = {"cases": {bc: compare(bc) for bc in args.bcs}}
    results["inputs"] = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()} | {"short": SHORT}
    results["machine"] = machine()
    results["command"] = " ".join(sys.argv)
    results["wall_time_s"] = time.perf_counter() - t0
    name = args.name
    (args.results / f"{name}.json").write_text(json.dumps(results, indent=1, default=float))
    plot(results)
    print(f"wrote {args.results / name}.json")
