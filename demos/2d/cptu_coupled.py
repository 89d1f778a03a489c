"""Saturated coupled cone penetration (2D CPTu): the pore pressure behind the cone (u2)
against depth at two push rates, drained, undrained and dry (a 3D scene too:
demos/3d/cptu_coupled.py runs this on scenes/cptu_3d.toml).

This demo shows how to:

- run the coupled cone penetration of ``scenes/cptu_2d.toml`` (a loose, contractive window
  of disks inside a micropolar FE chamber) saturated: one Darcy pore pressure over the whole
  chamber, its source the grains' (and the cone's) volumetric change in the window and the
  continuum's outside, acting on the free grains and, beyond the overlap, on the continuum
  (a Biot continuum in total stress; ``--continuum drained``: the dry one, to compare)
  (`coupling.apps.penetration.saturated`),
- read the excess pore pressure at the shoulder just above the cone (u2, as CPTu standards
  place the filter) and on the face (u1), the grains' tip resistance q_c (effective) and
  the total q_t = q_c + the pore pressure's push on the cone,
- set the drainage by the normalised velocity V = v d / c_v (c_v = k M / mu_f, M the
  packing's constrained modulus; drained below ~0.3, undrained above ~30: Randolph & Hope
  2004, DeJong & Randolph 2012), at two push rates of one permeability, a drained and an
  undrained permeability at the fast rate, and the dry run beside,
- write ``results.json`` and ``cptu_coupled.png`` (u2 and q_c against depth) to ``--out``.

Run: ``NUMBA_NUM_THREADS=1 python demos/2d/cptu_coupled.py`` (one core: ~3 min wall;
CPU ~9 s set-up and 13-25 s push a saturated run with the scene's fluid step every 25 DEM
steps, the DEM steps between taking the interval's forces in the DEM's own step loop
(`ChamberFlow.interval_response`), 5 s the dry push); ``--every 1``: the fluid every DEM
step, ~100-110 s a push (at V ~ 1 in 3 packings q_c 1.4 % above every 25's on average,
u2 alike: benchmarks/cptu_cost.py).
``GRANFE_SHORT=1``: a small window and cone
(the tests' scene), dry, drained and undrained only, ~10 s. The continuum's share of the
overlap stays drained, and the pressure round the cone is not mesh-converged (largest at
V ~ 30): see the module docstring of `coupling.apps.penetration.saturated`.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np

from coupling.apps.penetration.coupled import CoupledPenetration
from coupling.apps.penetration.penetrators import filtered, tip_height
from coupling.apps.penetration.saturated import SaturatedPenetration
from coupling.scene import load_scene

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))   # (the repository: benchmarks/)
from benchmarks.machine import machine  # noqa: E402

SHORT = os.environ.get("GRANFE_SHORT") == "1"

# ---- parameters (SI, per unit thickness) ------------------------------------------------------
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--scene", type=Path, default=Path("scenes/cptu_2d.toml"))
parser.add_argument("--depth", type=float, default=None,
                    help="push [m] (default 2D 0.045, short 0.012; 3D the scene's)")
parser.add_argument("--fast", type=float, default=0.2, help="fast push rate [m/s]")
parser.add_argument("--slow", type=float, default=0.1, help="slow push rate [m/s]")
parser.add_argument("--k", type=float, default=None,
                    help="the two rates' permeability [m^2] (default 2D 3e-11; 3D the scene's)")
parser.add_argument("--k-drained", type=float, default=None,
                    help="drained permeability [m^2] (default 100 --k)")
parser.add_argument("--k-undrained", type=float, default=None,
                    help="undrained permeability [m^2] (default 2D 9e-13, short 3e-13; 3D --k / 1000)")
parser.add_argument("--seed", type=int, default=None, help="the packing's seed (default: the scene's)")
parser.add_argument("--every", type=int, default=None,
                    help="DEM steps per fluid step (default: the scene's fluid.every)")
parser.add_argument("--response-every", type=int, default=None,
                    help="DEM steps per application of the interval's forces (default: the scene's "
                         "fluid.response_every)")
parser.add_argument("--continuum", choices=["biot", "drained"], default=None,
                    help="how the continuum takes the pore pressure (default: the scene's fluid.continuum)")
parser.add_argument("--runs", nargs="+", default=None,
                    help="a subset of dry, drained, fast, undrained, slow (default: all; 3D without undrained)")
parser.add_argument("--out", type=Path, default=Path("output/cptu_coupled"))
args = parser.parse_args()
comm = MPI.COMM_WORLD


def log(msg):
    if comm.rank == 0:
        print(msg, flush=True)


# short: a window of ~420 grains, a cone of 3 grain diameters, the DEM step at 0.2 of critical
# (4x the scene's), so a fluid step every 10 DEM steps (40 of the scene's step lengths; at 25,
# undrained (V = 51) u2 read -1.4 kPa against 2.2 with the fluid every DEM step, at 10 3.5)
SMALL = {"chamber": {"width": 0.16, "depth": 0.12, "element_size_window": 0.008, "element_size_far": 0.03},
         "grains": {"settle_time": 0.15}, "window": {"half_width": 0.025, "depth": 0.045, "handshake": 1.0},
         "penetrator": {"radius": 0.0045}, "coupling": {"dt_factor": 4.0},
         "fluid": {"every": 10, "response_every": 1}}   # (at the 4x step dt omega ~ 0.2: every step)
# short in 3D: ~2000 spheres round a cone of 2.5 grain radii, 16 mm of push
SMALL_3D = {"chamber": {"width": 0.1, "depth": 0.07, "element_size_far": 0.03},
            "grains": {"settle_time": 0.05}, "window": {"half_width": 0.016, "depth": 0.04},
            "penetrator": {"radius": 0.005, "depth": 0.016}, "coupling": {"relaxation": 0.3},
            "fluid": {"permeability": 1e-10, "every": 10, "saturation_time": 0.01}}
dim = load_scene(args.scene).scene.dimension
overrides = (SMALL if dim == 2 else SMALL_3D) if SHORT else {}
if args.seed is not None:
    overrides = {**overrides, "grains": {**overrides.get("grains", {}), "seed": args.seed}}
scene = load_scene(args.scene, overrides)
if args.depth is None:
    args.depth = (0.012 if SHORT else 0.045) if dim == 2 else scene.parameters().depth
prm0 = replace(scene.parameters(), depth=args.depth)
fluid0 = scene.fluid_parameters()
if args.k is None:
    args.k = 3e-11 if dim == 2 else fluid0.permeability
if args.k_drained is None:
    args.k_drained = 100 * args.k
if args.k_undrained is None:
    args.k_undrained = (3e-13 if SHORT else 9e-13) if dim == 2 else args.k / 1000
if args.every is not None:
    fluid0 = replace(fluid0, every=args.every)
if args.response_every is not None:
    fluid0 = replace(fluid0, response_every=args.response_every)
if args.continuum is not None:
    fluid0 = replace(fluid0, continuum=args.continuum)
runs = {"dry": (None, args.fast),
        "drained": (args.k_drained, args.fast),
        "fast": (args.k, args.fast),
        "undrained": (args.k_undrained, args.fast),
        "slow": (args.k, args.slow)}
# 3D: no undrained run by default. The pressure is one P1 field on the continuum's mesh, whose
# elements must hold several grains: the 3D cone is about one element wide, and undrained the
# pressure's error round it (of order (mu_f / k)(v / R) h^2, saturated.py) outgrows the
# effective stress: in the short 3D scene (GRANFE_SHORT=1) at V = 80 u_max climbed 5 -> 250 kPa over 11 mm of
# push and grains left at 15 m/s (the cone at 0.2 m/s), with the interval's forces at every DEM
# step as with once in 5. --runs undrained still runs it.
default = (["dry", "drained", "undrained"] if dim == 2 else ["dry", "drained", "fast"]) if SHORT else \
    (list(runs) if dim == 2 else ["dry", "drained", "fast", "slow"])
runs = {name: runs[name] for name in default} if args.runs is None else runs
if args.runs is not None:
    unknown = set(args.runs) - set(runs)
    if unknown:
        parser.error(f"--runs: unknown {sorted(unknown)}; choose from {sorted(runs)}")
    runs = {name: runs[name] for name in args.runs}


# ---- runs ---------------------------------------------------------------------------------------
def run(name, k, v):
    """One push; returns its record (figures and the depth profiles)."""
    prm = replace(prm0, velocity=v)
    t0 = time.process_time()
    if k is None:
        cpt = CoupledPenetration(prm, comm, log=lambda m: None)
    else:
        cpt = SaturatedPenetration(prm, replace(fluid0, permeability=k), comm, log=lambda m: None)
    t_setup = time.process_time() - t0
    t0 = time.process_time()
    history = cpt.run()
    cpu = time.process_time() - t0
    window = 2 * prm.cone_radius       # the profiles averaged over one cone diameter
    # u2's filter position is embedded once the shoulder is a grain radius below the surface
    embedded = tip_height(prm) + 2 * prm.radius
    rec = {"k": k, "velocity": v, "cpu_setup_s": t_setup, "cpu_push_s": cpu,
           "depth": [h["depth"] for h in history],
           "q_c": filtered(history, "q_c", window).tolist()}
    deep = np.array(rec["depth"]) > max(embedded, 0.5 * prm.depth)
    rec["q_c_mean"] = float(np.mean(np.array([h["q_c"] for h in history])[deep]))
    if k is not None:
        s = cpt.summary()
        rec.update(c_v=s["c_v"], V=s["V"], porosity=s["porosity_window"], fluid_wall_s=s["fluid_time_s"],
                   constrained_modulus=s["constrained_modulus"])
        for key in ("u1", "u2", "q_t", "q_u", "u_max"):
            rec[key] = filtered(history, key, window).tolist()
            rec[f"{key}_mean"] = float(np.mean(np.array([h[key] for h in history])[deep]))
    log(f"{name:9s} v = {v:5.3f} m/s" + (f", k = {k:.2g} m^2, V = {rec['V']:6.3g}" if k else " (dry)")
        + f": q_c {rec['q_c_mean'] / 1e3:6.2f} kPa"
        + (f", q_t {rec['q_t_mean'] / 1e3:7.2f} kPa, u2 {rec['u2_mean'] / 1e3:7.2f} kPa, "
           f"u1 {rec['u1_mean'] / 1e3:7.2f} kPa" if k else "")
        + f" (CPU {t_setup:.0f} s set-up, {cpu:.0f} s push)")
    return rec


t_start = time.perf_counter()
results = {name: run(name, k, v) for name, (k, v) in runs.items()}
wall = time.perf_counter() - t_start


# ---- outputs ------------------------------------------------------------------------------------
def figure(path):
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 5.5), sharey=True)
    colour = dict(zip(["dry", "drained", "slow", "fast", "undrained"], plt.cm.viridis([0.0, 0.25, 0.5, 0.7, 0.9]),
                      strict=True))   # (one colour a run in both panels, by drainage)
    colour["dry"] = "k"
    for name, rec in results.items():
        d = 100 * np.array(rec["depth"])
        label = name if rec["k"] is None else f"{name}: v {rec['velocity']} m/s, V = {rec['V']:.2g}"
        a2.plot(np.array(rec["q_c"]) / 1e3, d, label=label, color=colour[name])
        if rec["k"] is not None:
            a1.plot(np.array(rec["u2"]) / 1e3, d, label=label, color=colour[name])
            a2.plot(np.array(rec["q_t"]) / 1e3, d, ls="--", color=colour[name], lw=0.8)
    a1.axvline(0, color="0.6", lw=0.5)
    a1.axhline(100 * (tip_height(prm0) + 2 * prm0.radius), color="0.6", ls=":", lw=0.8)
    wet = [np.abs(rec["u2"]).max(initial=0.0) for rec in results.values() if rec["k"] is not None]
    if max(wet, default=0.0) > 1e3:   # (kPa-scale pressures: log beyond 1 kPa; below it linear)
        a1.set_xscale("symlog", linthresh=1.0)
    a2.set_xscale("symlog", linthresh=1.0)
    a1.set_xlabel("u2, excess pore pressure at the shoulder [kPa]")
    a2.set_xlabel("q_c (solid: grains) and q_t (dashed: + pore pressure) [kPa]")
    a1.set_ylabel("depth of the cone tip [cm]")
    a1.invert_yaxis()
    a1.legend(fontsize=7, loc="lower right")
    a2.legend(fontsize=7, loc="lower right")
    a1.set_title("averaged over one cone diameter; dotted: shoulder embedded", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if comm.rank == 0:
    args.out.mkdir(parents=True, exist_ok=True)
    summary = {name: {k: v for k, v in rec.items() if not isinstance(v, list)} for name, rec in results.items()}
    (args.out / "results.json").write_text(json.dumps(
        {"scene": str(args.scene), "depth": args.depth, "short": SHORT, "wall_s": wall, "machine": machine(),
         "runs": results, "summary": summary}, indent=1))
    figure(args.out / "cptu_coupled.png")
    log(f"{wall:.0f} s wall; outputs in {args.out}")

# ---- checks -------------------------------------------------------------------------------------
for name, rec in results.items():
    assert all(np.isfinite(rec["q_c"])), name
    if rec["k"] is not None:
        assert all(np.isfinite(rec["u2"])), name
if {"drained", "undrained"} <= set(results):
    # the drained run drains (V < 0.3) and the undrained one does not (V > 30)
    assert results["drained"]["V"] < 0.3 < 30 < results["undrained"]["V"]
    # contractive: the undrained excess pressure on the cone's face is positive, above the
    # drained one, and so is the total resistance
    for key in ("u1_mean", "q_t_mean"):
        assert results["undrained"][key] > max(results["drained"][key], 0.0), key
    # and behind it (u2): the full scene's 45 mm; the short push's few FE steps past the
    # shoulder's embedding leave u2 one packing's (seed 1 -0.6 kPa, seeds 2-5 4-11 kPa)
    if not SHORT:
        assert results["undrained"]["u2_mean"] > max(results["drained"]["u2_mean"], 0.0)
