"""Stress paths and principal stress axes rotation of a periodic RVE of spheres (seed 004 §4).

This demo shows how to:

- consolidate a periodic cell of spheres (seed 004 §4.1: diameters 0.03-0.07 mm, linear
  springs kn = 100 kN/m, kt = 70 kN/m, friction tan 15 deg) to the isotropic p0 = 100 kPa
  (`dem.rve.RVE.consolidate`),
- drive it under full stress control (`RVE.load`, every component prescribed) along the
  seed's stress paths A (triaxial at constant p), B (sigma_xx = p, sigma_yy and sigma_zz
  apart at constant p: b = 0.5) and C (unloaded to pc, then conventional triaxial
  compression up to A-2's stress),
- keep the states at the rotation points (A-1..3, B-1..2, C-2 of Fig. 8/9), and from each
  turn the principal stress axes at constant p, |s*| and b = 0.5 (eq. 58-60, 2 alpha = 0..360
  deg) after a change of Lode angle at constant p and |s*| where the point is triaxial,
- write the strain loci ((e_zz - e_yy)/2 against e_zy, Fig. 11/13/15) and the stress-strain
  curves of the paths (Fig. 10/12/14) to JSON and a PNG, and judge the seed's findings.

Soil sign convention in the outputs: compression positive (sigma' = -sigma, eps' = -eps).
Stress levels from Fig. 8: |s*|/p = 0.2 (A-1, B-1), 0.4 (A-2, B-2, C-2), 0.6 (A-3); pc
puts C-2 at A-2's stress: pc = p0 (1 - 0.4 / sqrt(6)) = 83.7 kPa. ``--level-scale`` moves
all levels (and pc) by one factor, for a cell weaker than the seed's.
Run: ``python demos/3d/seed004_stress_paths.py`` (``--quick``: a small cell, coarse steps,
A-1 only, under a minute).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import numpy as np

from dem.rve import RVE, ConvergenceError, Grains, QuasiStatic

SHORT = os.environ.get("GRANFE_SHORT") == "1"

# ---- parameters (SI) ------------------------------------------------------------------------
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--quick", action="store_true", default=SHORT,
                    help="small cell, coarse increments, point A-1 only (a test run)")
parser.add_argument("--spheres", type=int, default=None,
                    help="about this many spheres (seed: 1073; default 300, quick 100)")
parser.add_argument("--p0", type=float, default=100e3, help="isotropic pressure [Pa]")
parser.add_argument("--kn", type=float, default=100e3, help="normal spring [N/m]")
parser.add_argument("--kt", type=float, default=70e3, help="tangential spring [N/m]")
parser.add_argument("--friction-deg", type=float, default=15.0, help="contact friction angle")
parser.add_argument("--points", default=None,
                    help="rotation points, comma separated (default A-1,A-2,A-3,B-1,B-2,C-2)")
parser.add_argument("--rotation-steps", type=int, default=None,
                    help="increments of 2 alpha over 360 deg (default 24, quick 8)")
parser.add_argument("--consolidation-friction", type=float, default=0.1,
                    help="contact friction while consolidating (seed: no protocol; lower is "
                         "denser; the 0.27 of the grains gives a loose cell that fails near "
                         "|s*|/p = 0.4 under rotation)")
parser.add_argument("--level-scale", type=float, default=1.0,
                    help="multiply the seed's |s*|/p levels (0.2, 0.4, 0.6) by this, to put "
                         "them at the same fraction of a weaker cell's strength")
parser.add_argument("--seed", type=int, default=1)
parser.add_argument("--out", type=Path, default=Path("output/seed004_stress_paths"))
args = parser.parse_args()
args.out.mkdir(parents=True, exist_ok=True)
quick = args.quick
n_spheres = args.spheres or (100 if quick else 300)
points = (args.points or ("A-1" if quick else "A-1,A-2,A-3,B-1,B-2,C-2")).split(",")
n_rot = args.rotation_steps or (8 if quick else 24)
P0 = args.p0
LEVEL = {q: args.level_scale * lv for q, lv in
         {"A-1": 0.2, "A-2": 0.4, "A-3": 0.6, "B-1": 0.2, "B-2": 0.4, "C-2": 0.4}.items()}
PC = P0 * (1.0 - LEVEL["C-2"] / math.sqrt(6.0))  # C-2 at A-2's stress
PATH_STEP = 0.1 if quick else 0.05  # |s*|/p per increment on the proportional paths
grains = Grains(n=n_spheres, kn=args.kn, kt=args.kt,
                friction=math.tan(math.radians(args.friction_deg)), seed=args.seed,
                consolidation_friction=args.consolidation_friction)
solver = QuasiStatic(force_tol=1e-2 if quick else 2e-3, stress_tol=1e-2 if quick else 3e-3,
                     ramp_steps=200 if quick else 400, max_steps=20_000 if quick else 40_000)
ALL = np.ones((3, 3), bool)


def soil(t):
    """Compression positive."""
    return -np.asarray(t)


def dev_norm(t):
    d = t - np.trace(t) / 3.0 * np.eye(3)
    return float(np.sqrt(np.sum(d * d)))


def triaxial(p, q_norm):
    """sigma' (compression positive) of a triaxial state sigma_zz > sigma_xx = sigma_yy at
    mean p with |s*| = q_norm."""
    t = q_norm / math.sqrt(6.0)
    return np.diag([p - t, p - t, p + 2 * t])


def rotation_state(p, q_norm, two_alpha):
    """Eq. 58-60 (b = 0.5, sigma_xx = sigma_2 = p): sigma' at 2 alpha [rad], |s*| = q_norm."""
    r = q_norm / math.sqrt(2.0)
    s = np.diag([p, p - r * math.cos(two_alpha), p + r * math.cos(two_alpha)])
    s[1, 2] = s[2, 1] = r * math.sin(two_alpha)
    return s


# ---- set-up: the consolidated cell ----------------------------------------------------------
t_start = time.perf_counter()
rve = RVE.consolidate(grains, P0, solver)
iso = soil(rve.stress())
packing = dict(stress=iso.tolist(), solid_fraction=rve.solid_fraction(),
               contacts_per_grain=rve.coordination(), steps=rve.sim.nsteps)
print(f"consolidated {rve.sim.p.n} spheres to p = {np.trace(iso) / 3:.5g} Pa in "
      f"{rve.sim.nsteps} steps (solid fraction {rve.solid_fraction():.3f}, "
      f"{rve.coordination():.2f} contacts a grain, dt = {rve.sim.dt:.3g} s)", flush=True)
stats = dict(steps=0, increments=0, worst_stress_error=0.0)


def go(target):
    """One stress-controlled increment to sigma' = target (all components)."""
    info = rve.load(stress=-target, mask=ALL)
    stats["steps"] += info["steps"]
    stats["increments"] += 1
    stats["worst_stress_error"] = max(stats["worst_stress_error"], info["stress_error"])
    return info


def record():
    s, e = soil(rve.stress()), soil(rve.strain())
    p = np.trace(s) / 3.0
    return dict(p=p, q_over_p=dev_norm(s) / p, eps_dev=dev_norm(e), eps_v=float(np.trace(e)),
                stress=s.tolist(), strain=e.tolist())


def proportional(targets, name):
    """Follow the stress targets, recording; stop at a failure (runaway strain)."""
    rows = []
    for t in targets:
        try:
            go(t)
        except ConvergenceError as err:
            print(f"  path {name}: no equilibrium at |s*|/p = {dev_norm(t) / np.trace(t) * 3:.2f}"
                  f" ({err})")
            rve.restore()
            return rows, False
        rows.append(record())
        rve.commit()
    return rows, True


def levels(top):
    """|s*|/p of the increments up to top: every PATH_STEP and the rotation levels."""
    grid = [PATH_STEP * k for k in range(1, int(top / PATH_STEP + 1e-9) + 1)]
    marks = [lv for lv in LEVEL.values() if lv <= top + 1e-12] + [top]
    return sorted({round(v, 12) for v in grid + marks})


# ---- solve: the paths, keeping the rotation points -------------------------------------------
origin = rve.state_dict()
saved, curves = {}, {}
want = {"A": max([LEVEL[q] for q in points if q[0] == "A"], default=0.0),
        "B": max([LEVEL[q] for q in points if q[0] == "B"], default=0.0)}
for name, state_of in (("A", lambda lv: triaxial(P0, lv * P0)),
                       ("B", lambda lv: rotation_state(P0, lv * P0, 0.0))):
    if want[name] == 0.0:
        continue
    rve.load_state(origin)
    rve.commit()
    rows = []
    for lv in levels(want[name]):
        r, ok = proportional([state_of(lv)], name)
        rows += r
        if not ok:
            break
        for q in points:
            if q[0] == name and abs(LEVEL[q] - lv) < 1e-9:
                saved[q] = rve.state_dict()
    curves[name] = rows
    print(f"path {name}: {len(rows)} increments, |s*|/p up to "
          f"{rows[-1]['q_over_p'] if rows else 0:.3f}", flush=True)
if "C-2" in points:
    rve.load_state(origin)
    rve.commit()
    rows, ok = proportional([np.eye(3) * (P0 + (PC - P0) * k / 2) for k in (1, 2)], "C")
    n_c = len(levels(LEVEL["C-2"]))  # conventional triaxial from pc up to C-2
    rows2, ok2 = proportional([np.diag([PC, PC, PC + 3 * (P0 - PC) * k / n_c])
                               for k in range(1, n_c + 1)], "C") if ok else ([], False)
    curves["C"] = rows + rows2
    if ok and ok2:
        saved["C-2"] = rve.state_dict()
    print(f"path C: unloaded to pc = {PC:.4g} Pa, loaded to |s*|/p = "
          f"{curves['C'][-1]['q_over_p']:.3f}", flush=True)


def rotate(q):
    """From the saved state of point q: to b = 0.5 at constant p and |s*| (Lode angle
    turned along the deviatoric circle), then 2 alpha = 0..360 deg. Returns the locus."""
    rve.load_state(saved[q])
    rve.commit()
    s0 = soil(rve.stress())
    p, qn = np.trace(s0) / 3.0, dev_norm(s0)
    start = rotation_state(p, qn, 0.0)
    d0, d1 = s0 - p * np.eye(3), start - p * np.eye(3)
    if np.abs(d1 - d0).max() > 1e-6 * p:  # triaxial (b = 0) -> b = 0.5
        for lam in np.linspace(0, 1, 5)[1:]:
            d = (1 - lam) * d0 + lam * d1
            try:
                go(p * np.eye(3) + qn * d / np.sqrt(np.sum(d * d)))
            except ConvergenceError as err:
                print(f"  {q}: no equilibrium turning the Lode angle to b = 0.5 ({err})")
                return dict(locus=[], complete=False, note=f"no equilibrium at b = 0.5 (Lode "
                            f"angle turned {lam:.2f} of the way) within max_steps: the cell creeps "
                            f"(yields, or settles too slowly) ({err})")
    e0 = soil(rve.strain())
    locus, held = [dict(two_alpha_deg=0.0, x=0.0, y=0.0)], 0.0
    for k in range(1, n_rot + 1):
        ta = 2 * math.pi * k / n_rot
        target = rotation_state(p, qn, ta)
        try:
            go(target)
        except ConvergenceError as err:
            print(f"  {q}: no equilibrium at 2 alpha = {math.degrees(ta):.0f} deg ({err})")
            return dict(locus=locus, complete=False, note=f"no equilibrium at 2 alpha = "
                        f"{math.degrees(ta):.0f} deg within max_steps: the cell creeps (yields, "
                        f"or settles too slowly) ({err})")
        e = soil(rve.strain()) - e0
        held = max(held, float(np.abs(soil(rve.stress()) - target).max()))
        locus.append(dict(two_alpha_deg=math.degrees(ta), x=0.5 * (e[2, 2] - e[1, 1]),
                          y=e[1, 2]))
    return dict(locus=locus, complete=True, p=p, s_norm=qn, stress_error_max=held)


loci = {}
for q in points:
    if q not in saved:
        loci[q] = dict(locus=[], complete=False, note="rotation point not reached")
        continue
    t0 = time.perf_counter()
    loci[q] = rotate(q)
    lc = loci[q]["locus"] or [dict(x=0.0, y=0.0)]
    print(f"rotation {q}: {len(lc) - 1} increments, last strain "
          f"({lc[-1]['x'] * 100:.4f}, {lc[-1]['y'] * 100:.4f}) % in "
          f"{time.perf_counter() - t0:.0f} s", flush=True)


# ---- results: the seed's findings, point by point -------------------------------------------
def shape(q):
    """End-of-cycle offset |e(360) - e(0)|, size (largest distance from the centroid of the
    loop) and roundness (smallest / largest distance from the centroid) of a locus."""
    lc = loci.get(q, {}).get("locus", [])
    if not loci.get(q, {}).get("complete"):
        return None
    xy = np.array([[r["x"], r["y"]] for r in lc])
    c = xy[:-1].mean(axis=0)
    rad = np.linalg.norm(xy[:-1] - c, axis=1)
    return dict(offset=float(np.linalg.norm(xy[-1] - xy[0])), size=float(rad.max()),
                roundness=float(rad.min() / rad.max()), xy=xy)


shapes = {q: shape(q) for q in points}
findings = []
for q in ("A-1", "B-1"):
    s = shapes.get(q)
    if s is not None:
        ok = s["roundness"] > 0.6 and s["offset"] < 0.5 * s["size"]
        findings.append(dict(
            claim=f"{q}: a circular locus near the isotropic state", holds=bool(ok),
            measured=f"roundness {s['roundness']:.2f} (min/max radius), end offset "
                     f"{s['offset'] * 100:.4f} % for a radius {s['size'] * 100:.4f} %"))
def offset(q):
    """End-of-cycle offset of a completed locus; inf where the cell yielded under rotation
    (no equilibrium: the strain runs away), None where the point was not reached."""
    if shapes.get(q) is not None:
        return shapes[q]["offset"]
    return math.inf if loci.get(q, {}).get("note", "").startswith("no equilibrium") else None


for series in (("A-1", "A-2", "A-3"), ("B-1", "B-2")):
    got = [(q, offset(q)) for q in series if q in points and offset(q) is not None]
    if len(got) >= 2 and math.isfinite(got[0][1]):
        grows = all(a[1] < b[1] for a, b in zip(got, got[1:], strict=False))
        findings.append(dict(
            claim=f"end-of-cycle inelastic strain grows with the deviator ({', '.join(series)})",
            holds=bool(grows),
            measured=", ".join(f"{q}: {o * 100:.4f} %" if math.isfinite(o) else
                               f"{q}: no equilibrium under rotation (creeps)"
                               for q, o in got)))
if shapes.get("A-2") is not None and shapes.get("C-2") is not None:
    a, c = shapes["A-2"]["xy"], shapes["C-2"]["xy"]
    d_ac = float(np.sqrt(np.mean(np.sum((a - c) ** 2, axis=1))))
    scale = shapes["A-2"]["size"]
    d_ab = None
    if shapes.get("B-2") is not None:
        d_ab = float(np.sqrt(np.mean(np.sum((a - shapes["B-2"]["xy"]) ** 2, axis=1))))
    findings.append(dict(
        claim="C-2 ~ A-2: the rotation response does not depend on the mean-stress history",
        holds=bool(d_ac < 0.3 * scale and (d_ab is None or d_ac < d_ab)),
        measured=f"RMS distance A-2/C-2 {d_ac * 100:.4f} % for a locus radius "
                 f"{scale * 100:.4f} %" + ("" if d_ab is None else
                                           f"; A-2/B-2 {d_ab * 100:.4f} %")))
for q in points:
    if shapes.get(q) is None:
        findings.append(dict(claim=f"{q}: a complete rotation cycle", holds=False,
                             measured=loci[q].get("note", "stopped")))
for f in findings:
    print(f"{'HOLDS' if f['holds'] else 'DOES NOT HOLD'}: {f['claim']} ({f['measured']})")

results = dict(
    seed="004 (Tsutsumi & Kaneko 2008), §4",
    inputs=dict(spheres=int(rve.sim.p.n), seed_spheres=1073, d_min=grains.d_min,
                d_max=grains.d_max, kn=grains.kn, kt=grains.kt, friction=grains.friction,
                density=grains.density, restitution=grains.restitution, p0=P0, pc=PC,
                levels=LEVEL, rotation_increments=n_rot, path_step=PATH_STEP,
                solver=solver.__dict__, dt=rve.sim.dt, quick=quick,
                convention="compression positive; strains sym(F) - I from the consolidated cell"),
    consolidated=packing,
    paths=curves,
    rotations=loci,
    findings=findings,
    totals=dict(stats, wall_time_s=time.perf_counter() - t_start),
)
(args.out / "results.json").write_text(json.dumps(results, indent=1))

# ---- plots ------------------------------------------------------------------------------------
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

fig, ax = plt.subplots(2, 2, figsize=(11, 10))
for name, rows in curves.items():
    ax[0, 0].plot([0] + [r["eps_dev"] * 100 for r in rows], [0] + [r["q_over_p"] for r in rows],
                  "o-", ms=3, label=f"path {name}")
ax[0, 0].set(xlabel="||e*|| (%)", ylabel="||s*|| / p", title="paths (Fig. 10, 12, 14)")
ax[0, 0].legend()
panels = [(ax[0, 1], ("A-1", "A-2", "A-3"), "Fig. 11"), (ax[1, 0], ("B-1", "B-2"), "Fig. 13"),
          (ax[1, 1], ("A-2", "B-2", "C-2"), "Fig. 15")]
for a, names, fig_name in panels:
    for q in names:
        lc = loci.get(q, {}).get("locus", [])
        if lc:
            a.plot([r["x"] * 100 for r in lc], [r["y"] * 100 for r in lc], "o-", ms=2.5,
                   label=q + ("" if loci[q]["complete"] else " (stopped)"))
        else:
            a.plot([], [], label=f"{q} (not run)")
    a.set(xlabel="(e_zz - e_yy) / 2 (%)", ylabel="e_zy (%)",
          title=f"rotation of principal axes, b = 0.5 ({fig_name})")
    a.axhline(0, color="0.8", lw=0.5)
    a.axvline(0, color="0.8", lw=0.5)
    a.set_aspect("equal", "datalim")
    a.xaxis.set_major_locator(plt.MaxNLocator(5))
    a.legend()
fig.suptitle(f"seed 004 stress paths: periodic RVE of {rve.sim.p.n} spheres, p0 = {P0 / 1e3:g} kPa")
fig.tight_layout()
fig.savefig(args.out / "seed004_stress_paths.png", dpi=110)
print(f"wrote {args.out / 'results.json'} and seed004_stress_paths.png in "
      f"{time.perf_counter() - t_start:.0f} s")

# ---- checks -----------------------------------------------------------------------------------
assert abs(np.trace(iso) / 3 - P0) <= solver.stress_tol * P0 * 1.01, "consolidated to p0"
assert np.abs(iso - np.trace(iso) / 3 * np.eye(3)).max() <= solver.stress_tol * P0 * 1.01
assert stats["worst_stress_error"] <= solver.stress_tol * 1.2 * P0, "prescribed stresses held"
assert all(loci[q]["complete"] for q in points if q in ("A-1", "B-1")), \
    "rotations near the isotropic state must complete"
