"""Micromorphic stress measures under a penetrating pile (seed 002 §3.1, Fig. 4-5).

This demo shows how to:

- build a polydisperse quartz-sand bed (Table 1 radii) from a jittered fcc lattice and let
  it settle under gravity in a box,
- push a rigid pile (a clump of GHOST spheres with a rounded tip; the paper uses one large
  ellipsoid) down through the bed at constant speed,
- record, every k steps, the stress measures of a fixed averaging domain below the pile
  split into 2 x 2 x 2 RVEs: micro-stress s, couple stress m, the Cauchy stress sigma from
  the balance of first moment of momentum (with/without micro-spin inertia and body
  couple) and the unsymmetric granular stress sigma^G (`dem.stress`, eq. 1-15),
- write the particles as a VTU/PVD series, a PNG render and the stress history plot.

Stiffness is scaled: E = 2.9e8 Pa instead of 2.9e10 Pa (Table 1), so the time step is 10x
larger (quoted in results.json). Serial only (a DEM-only demo).
Run: ``python demos/3d/pile_penetration_stress.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from dem import GHOST, ContactMaterial, Particles, Simulation, box_walls
from dem.io import ParticleWriter, render_png
from dem.packing import lattice_packing
from dem.stress import AveragingDomain, StressRecorder

SHORT = os.environ.get("GRANFE_SHORT") == "1"

# ---- parameters (SI) ------------------------------------------------------------------------
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--width", type=float, default=0.03 if SHORT else 0.05, help="box side [m]")
parser.add_argument("--fill-height", type=float, default=0.05 if SHORT else 0.08,
                    help="height of the initial lattice [m]")
parser.add_argument("--r-max", type=float, default=0.0025, help="largest radius [m]")
parser.add_argument("--r-min", type=float, default=0.002,
                    help="smallest radius [m] (Table 1: 1 mm; larger keeps the lattice dense)")
parser.add_argument("--E", type=float, default=2.9e8, help="Young's modulus (scaled) [Pa]")
parser.add_argument("--nu", type=float, default=0.25)
parser.add_argument("--density", type=float, default=2650.0, help="G = 2.65 [kg/m^3]")
parser.add_argument("--friction", type=float, default=0.5)
parser.add_argument("--damping-ratio", type=float, default=0.05, help="contact damping ratio")
parser.add_argument("--settle-time", type=float, default=0.05 if SHORT else 0.08,
                    help="settling time under gravity [s]")
parser.add_argument("--pile-radius", type=float, default=0.006, help="pile shaft radius [m]")
parser.add_argument("--pile-speed", type=float, default=0.5, help="[m/s]")
parser.add_argument("--depth", type=float, default=0.012 if SHORT else 0.025,
                    help="penetration of the tip below the initial surface [m]")
parser.add_argument("--domain-top", type=float, default=0.004 if SHORT else 0.005,
                    help="depth of the averaging domain's top below the surface [m]")
parser.add_argument("--domain-height", type=float, default=0.01 if SHORT else 0.015, help="[m]")
parser.add_argument("--domain-half-width", type=float, default=0.008 if SHORT else 0.01,
                    help="[m]")
parser.add_argument("--record-every", type=int, default=100, help="steps between records")
parser.add_argument("--out", type=Path, default=Path("output/pile_penetration_stress"))
args = parser.parse_args()
args.out.mkdir(parents=True, exist_ok=True)
g = np.array([0.0, 0.0, -9.81])


def restitution(zeta):
    """Coefficient of restitution of a linear contact with damping ratio zeta."""
    return float(np.exp(-np.pi * zeta / np.sqrt(1.0 - zeta**2)))


# ---- set-up: a settled bed ------------------------------------------------------------------
t0 = time.perf_counter()
W = args.width
x, r = lattice_packing((0, 0, 0), (W, W, args.fill_height), args.r_max, "fcc", gap=0.02,
                       jitter=1.0, seed=1)
rng = np.random.default_rng(2)
r = r * rng.uniform(args.r_min / args.r_max, 1.0, len(r))  # smaller than the sites: no overlap
walls = box_walls((0, 0, 0), (W, W, 1.0))
settling = ContactMaterial(E=args.E, nu=args.nu, density=args.density,
                           friction=args.friction, restitution=0.2)
grains = Particles.spheres(x, r, args.density)
sim = Simulation(grains, settling, walls, gravity=g)
sim.step(int(args.settle_time / sim.dt))
surface = float(np.quantile(grains.x[:, 2] + grains.radius, 0.98))
v_settled = float(np.linalg.norm(grains.v, axis=1).max())
print(f"settled {grains.n} grains in {sim.nsteps} steps, surface at z = {surface:.4f} m, "
      f"largest speed {v_settled:.3g} m/s")

# ---- the pile: a clump of ghost spheres (hexagonal rings of r_max spheres) -----------------
rp, rs = args.pile_radius, args.r_max
ring = [(0.0, 0.0)] + [((rp - rs) * np.cos(a), (rp - rs) * np.sin(a))
                       for a in np.linspace(0, 2 * np.pi, 7)[:-1]]
tip_z = surface + 2 * rs  # start just above the bed
levels = tip_z + rs + np.arange(0.0, args.depth + 0.02, rs)
pile_x = [(W / 2, W / 2, tip_z)] + [(W / 2 + a, W / 2 + b, z) for z in levels for a, b in ring]
pile_x = np.array(pile_x)
n_g = grains.n
x_all = np.vstack([grains.x, pile_x])
kind = np.r_[np.zeros(n_g, np.int8), np.full(len(pile_x), GHOST, np.int8)]
v_all = np.vstack([grains.v, np.tile([0.0, 0.0, -args.pile_speed], (len(pile_x), 1))])
p = Particles.spheres(x_all, np.r_[grains.radius, np.full(len(pile_x), rs)], args.density,
                      v=v_all, omega=np.vstack([grains.omega, np.zeros((len(pile_x), 3))]),
                      kind=kind)
quartz = ContactMaterial(E=args.E, nu=args.nu, density=args.density, friction=args.friction,
                         restitution=restitution(args.damping_ratio))
sim = Simulation(p, quartz, walls, gravity=g, allow_overlap=True)
pile = np.flatnonzero(kind == GHOST)

# averaging domain: a fixed box on the pile axis in the initial penetration zone
half, top = args.domain_half_width, surface - args.domain_top
if top - args.domain_height < 2 * rs or surface - args.depth < 4 * rs:
    raise ValueError(f"bed too shallow (surface z = {surface:.4f} m) for the averaging domain "
                     f"and penetration depth; raise --fill-height")
domain = AveragingDomain((W / 2 - half, W / 2 - half, top - args.domain_height),
                         (W / 2 + half, W / 2 + half, top), (2, 2, 2))
rec = StressRecorder(domain, args.out, "pile_stress", every=args.record_every,
                     gravity=tuple(g), on_empty="zero")
writer = ParticleWriter(args.out / "vtu", "pile")

# ---- solve: constant-speed penetration ------------------------------------------------------
n_steps = int((args.depth + 2 * rs) / args.pile_speed / sim.dt)
for step in range(n_steps + 1):
    if step % args.record_every == 0:
        pairs, force = sim.contact_forces()
        rec(step, sim.time, p.x, p.radius, pairs, force, p.mass, v=p.v)
    if step % (n_steps // 5) == 0:
        writer.write(sim.time, p.x, p.radius, velocity=p.v, omega=p.omega, force=p.force,
                     kind=p.kind)
    p.x[pile] += sim.dt * p.v[pile]  # prescribed pile motion (GHOST kind)
    sim.step(1)
writer.close()
paths = rec.write()
f_grain = np.where(kind == GHOST, 0.0, np.linalg.norm(p.force, axis=1))  # clump forces hidden
render_png(args.out / "pile_final.png", p.x, p.radius, scalars=f_grain, scalar_name="|F| [N]",
           view="xz", title="pile penetration: net contact force on the grains")
wall_time = time.perf_counter() - t0

# ---- results and checks ---------------------------------------------------------------------
rows = rec.rows
tens = rec.tensors
p_s = np.array([row["p_s"] for row in rows])
sym_err = max(np.abs(0.5 * (np.array(t["sigma_G"]) + np.array(t["sigma_G"]).T)
                     - np.array(t["s"])).max() for t in tens)
results = dict(
    inputs={k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
    n_grains=int(n_g), n_pile_spheres=int(len(pile)), dt=sim.dt, steps=n_steps,
    stiffness_scaling_vs_table1=2.9e10 / args.E, surface_z=surface, v_settled=v_settled,
    domain=dict(lo=list(domain.lo), hi=list(domain.hi), divisions=list(domain.divisions)),
    p_s_initial=float(p_s[0]), p_s_most_compressive=float(p_s.min()),
    max_abs_sym_sigmaG_minus_s=float(sym_err), history=rows, wall_time_s=wall_time,
    files={k: str(v) for k, v in paths.items()})
(args.out / "results.json").write_text(json.dumps(results, indent=1))
print(f"p_s: initial {p_s[0]:.4g} Pa, most compressive {p_s.min():.4g} Pa; "
      f"records {len(rows)}; wall time {wall_time:.1f} s; outputs in {args.out}")

assert all(np.isfinite(list(row.values())).all() for row in
           [{k: v for k, v in row.items() if isinstance(v, float)} for row in rows])
assert sym_err <= 1e-9 * max(1.0, np.abs(p_s).max()), "sym(sigma^G) must equal s"
assert p_s.min() < 2.0 * min(p_s[0], -1.0), "penetration must raise the compression below it"
