"""Terzaghi consolidation of a column of grains in a Darcy pore fluid (seed 003).

This demo shows how to:

- build a column of disks in a box (by default a hexagonal lattice of equal disks as wide
  as the box, whose skeleton is elastic, as Terzaghi's theory takes it; ``--packing
  random``: a random packing settled under gravity), then preload it by a surcharge shared
  by its surface grains (no gravity from then on: a uniform preload, as in an oedometer),
  loaded to the final load once and unloaded, so that the load step is a reload,
- measure the column's drained oedometric modulus (a dry load step: damped, then a slow
  undamped ramp as the saturated skeleton is loaded) and its permeability (a steady Darcy
  flow through it, :class:`coupling.pore_fluid.DarcyFlow`, before and after the dry step:
  Kozeny-Carman falls ~20 % over the step, c_v takes the mean) on the same packing,
- load the saturated column by a step of the surcharge with a drained top and an
  impermeable base, the fluid's pressure solved every ``--every`` DEM steps, its drag
  implicit in each DEM step,
- compare the settlement and the base pore pressure with Terzaghi's series solution for
  the measured c_v = k E_oed / mu_f; the layers' settlement shows where they differ,
- write ``results.json`` and ``grain_consolidation.png`` to ``--out``.

Why a lattice. A random 2D packing's reload is not elastic: its settlement depends on the
path (the saturated column is loaded from the drained face down, by seepage forces; the dry
one at once), so no measured modulus describes it. Measured, seeds 1-5 of the random
packing: the saturated column ends 0.95-1.22 times the dry settlement, max |U - U_T| 3-30 %
over T = 0.1-1.5, with either normal dashpot (the half-step one gave 2.7 % at seed 3 and 14
and 30 % at seeds 4 and 5), with one fluid step per DEM step as with eight, with grain
friction 1 or 100 and frictionless walls. The lattice reloads elastically (the ramped and
the damped dry steps settle alike, the saturated column ends at the dry settlement) and
tests the coupling itself: there the porosity averaged on P1 (nodal) runs ahead of
Terzaghi (T50 0.14 against 0.197: the nodes at the drained face and the base average one
side only, the boundary layer of grains, whose porosity and Kozeny-Carman permeability are
the column's highest), and the cell binning (DG0, the default) follows it. What is left
(the settlement a few % behind Terzaghi's from T ~ 0.3) is the grain column's own: the same
lattice under the closed-form 1D drag of the fluid alone (no pressure solve) settles the
same to 0.005 of U (tests/coupling/test_pore_fluid.py).

Run: ``python demos/2d/grain_consolidation.py`` (serial only: the DEM and the mesh are on
one rank; ~1.5 min); ``GRANFE_SHORT=1`` for a short run (to T = 0.5).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
from dolfinx import mesh

from coupling.pore_fluid import DarcyFlow, PoreFluidParameters, grain_volumes
from dem import ContactMaterial, Particles, Simulation, box_walls, relax
from dem.packing import lattice_packing, random_packing
from granfe.consolidation import terzaghi_pressure
from granfe.probe import probe

SHORT = os.environ.get("GRANFE_SHORT") == "1"

# ---- parameters (SI) ------------------------------------------------------------------
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--packing", choices=("lattice", "random"), default="lattice",
                    help="a hexagonal lattice of disks of radius r_max (the width rounded "
                         "to whole disks), or a random packing settled under gravity")
parser.add_argument("--width", type=float, default=0.04, help="column width W [m]")
parser.add_argument("--fill", type=float, default=0.04, help="height of the box filled [m]")
parser.add_argument("--r-min", type=float, default=0.9e-3, help="smallest radius [m]")
parser.add_argument("--r-max", type=float, default=1.1e-3, help="largest radius [m]")
parser.add_argument("--kn", type=float, default=2e4, help="normal contact stiffness [N/m]")
parser.add_argument("--wall-friction", type=float, default=None,
                    help="grain-wall friction (default: the grains')")
parser.add_argument("--preload", type=float, default=200.0, help="preload q0 [Pa]")
parser.add_argument("--load", type=float, default=200.0, help="load step dq [Pa]")
parser.add_argument("--mu-f", type=float, default=1e-3, help="fluid viscosity [Pa s]")
parser.add_argument("--beta-f", type=float, default=4.5e-10,
                    help="fluid compressibility [1/Pa] (water: 4.5e-10)")
parser.add_argument("--every", type=int, default=8,
                    help="DEM steps per fluid step (any: the drag is implicit in the DEM steps)")
parser.add_argument("--T-end", type=float, default=None, help="end time c_v t / H^2")
parser.add_argument("--rows", type=int, default=6, help="mesh rows (one column of quads)")
parser.add_argument("--layers", type=int, default=4,
                    help="layers of the settlement profile (diagnostics)")
parser.add_argument("--porosity-space", default="DG0",
                    help="DG0 or P1 (see coupling.pore_fluid; P1 runs ahead, the docstring)")
parser.add_argument("--headroom", type=float, default=0.0,
                    help="the mesh's (drained) top above the column's, in r_max (2: a "
                         "half-empty top cell, whose porosity inflates the surface grains' "
                         "seepage force 1 / (1 - n): the surface runs ahead, T50 0.147)")
parser.add_argument("--modulus", choices=("ramped", "damped"), default="ramped",
                    help="the drained step: a slow undamped ramp, or a damped step")
parser.add_argument("--overconsolidate", type=int, default=1,
                    help="1: load to the final load and unload before the step (a reload)")
parser.add_argument("--k-from", choices=("mean", "before"), default="mean",
                    help="c_v from the mean permeability of the packing before and after the "
                         "dry step, or from the one before")
parser.add_argument("--seed", type=int, default=3)
parser.add_argument("--out", type=Path, default=Path("output/grain_consolidation"))
args = parser.parse_args()
comm = MPI.COMM_SELF            # the DEM is serial here; the fluid solve too
T_END = args.T_end or (0.5 if SHORT else 1.5)
MAT = ContactMaterial(E=1e7, nu=0.25, density=2650.0, friction=0.3, restitution=0.3,
                      law="linear", kn=args.kn, kt=0.5 * args.kn)
FLUID = PoreFluidParameters(viscosity=args.mu_f, compressibility=args.beta_f,
                            porosity_space=args.porosity_space)
WALLS = dataclasses.replace(MAT, friction=MAT.friction if args.wall_friction is None
                            else args.wall_friction)   # the pair takes the smaller
# a lattice as wide as the box: its full rows touch both walls and cannot spread
W = args.width if args.packing == "random" else \
    2 * args.r_max * max(2, round(args.width / (2 * args.r_max)))


def log(msg):
    if MPI.COMM_WORLD.rank == 0:
        print(msg, flush=True)


def column(state=None):
    """The settled column as a fresh Simulation without gravity (from ``state`` if given):
    a floor and two side walls, no lid; the load is a surcharge on the top grains."""
    p = Particles.spheres(packed[0], packed[1], MAT.density, dim=2)
    sim = Simulation(p, [MAT, WALLS], walls=box_walls([0, 0, 0], [W, 1, 0], dim=2, material=1),
                     safety=0.1, allow_overlap=True)
    if state is not None:
        sim.load_state(state)
    return sim


def top_grains(x, r):
    """The grains whose top lies within 1.5 diameters of the highest: the loaded surface
    layer (a grain left out there would be washed out by the steep gradient under the
    drained face at the load step, as it would be without a porous platen)."""
    return np.flatnonzero(x[:, 1] + r > (x[:, 1] + r).max() - 3 * r.max())


def surcharge(q):
    """(n, 3) forces [N]: q W shared equally by the surface grains (q [Pa] downwards)."""
    f = np.zeros((len(packed[1]), 3))
    f[top, 1] = -q * W / len(top)
    return f


def surface(sim):
    """Mean height [m] of the surface grains' centres."""
    return float(sim.p.x[top, 1].mean())


def hold(sim, q, max_steps=100_000):
    """Damped steps under the surcharge q [Pa] until the surface moves less than 1e-9 m in
    200 steps (``relax`` needs gravity or walls to judge balance by)."""
    sim.set_external_force(np.arange(sim.p.n), surcharge(q))
    decay = np.exp(-0.02)
    last = surface(sim)
    for k in range(1, max_steps + 1):
        sim.p.v[:] *= decay
        sim.p.omega[:] *= decay
        sim.step(1)
        if k % 200 == 0:
            if abs(surface(sim) - last) < 1e-9:
                return k
            last = surface(sim)
    raise RuntimeError(f"the column did not come to rest under {q} Pa in {max_steps} steps")


# ---- 1. settle under gravity, then preload the surface --------------------------------
t_start = time.perf_counter()
if args.packing == "lattice":
    x, r = lattice_packing([0, 0], [W, args.fill], args.r_max, kind="hex")
else:
    x, r = random_packing([0, 0], [W, args.fill], args.r_min, args.r_max, 0.45,
                          seed=args.seed, strict=False)
p = Particles.spheres(x, r, MAT.density, dim=2)
sim = Simulation(p, [MAT, WALLS], walls=box_walls([0, 0, 0], [W, 1, 0], dim=2, material=1),
                 gravity=(0, -9.81),
                 safety=0.1)
if args.packing == "random":
    relax(sim, tol=1e-3, check_every=200)
packed = (p.x.copy(), p.radius.copy())
top = top_grains(*packed)
sim = column()
if args.overconsolidate:
    # loaded to the final load once and unloaded: the load step is then a reload, which a
    # granular skeleton takes nearly elastically (a first loading also collapses it, faster
    # where the effective stress rises first: the surface runs ahead of Terzaghi's)
    hold(sim, args.preload + args.load)
hold(sim, args.preload)
preloaded = sim.state_dict()
H0 = float((sim.p.x[:, 1] + sim.p.radius).max())     # the column's height
H_MESH = H0 + args.headroom * args.r_max      # the drained top
y0 = surface(sim)
V = grain_volumes(p.radius, 2)
porosity = 1 - V.sum() / (W * H0)
log(f"{p.n} grains ({len(top)} loaded), column H = {1e3 * H0:.2f} mm, porosity {porosity:.4f}")

# ---- 2. drained oedometric modulus: a dry load step -----------------------------------
sim = column(preloaded)
y_pre = sim.p.x[:, 1].copy()
edges = np.linspace(0, H0, args.layers + 1)
in_layer = np.clip(np.searchsorted(edges, y_pre) - 1, 0, args.layers - 1)


def layer_settlement(y):
    """Mean downward displacement [m] of the grains of each layer (by preloaded height)."""
    d = y_pre - y
    return np.bincount(in_layer, d, args.layers) / np.bincount(in_layer, None, args.layers)


hold(sim, args.preload + args.load)
loaded = sim.state_dict()
s_drained = y0 - surface(sim)
u_dry = layer_settlement(sim.p.x[:, 1])
E_oed = args.load * H0 / s_drained
log(f"drained settlement {1e6 * s_drained:.2f} um: E_oed = {E_oed:.4g} Pa")

# ---- 3. permeability: steady upward flow through the column, before and after the step --
# a 1D problem: full-width rows of ~30 grains each (the porosity's averaging volume)
msh = mesh.create_rectangle(comm, [[0, 0], [W, H_MESH]], [1, args.rows],
                            mesh.CellType.quadrilateral)


def permeability(state, dp=10.0):
    """k [m^2] of the column in ``state`` from the flux of a steady flow under dp [Pa]."""
    sim = column(state)
    flow = DarcyFlow(msh, sim, PoreFluidParameters(viscosity=args.mu_f, compressibility=0.0,
                                                    porosity_space=args.porosity_space))
    flow.pressure(lambda X: np.isclose(X[1], 0.0), dp)
    flow.drained(lambda X: np.isclose(X[1], H_MESH))
    flow.solve()
    height = float((sim.p.x[:, 1] + sim.p.radius).max())
    return flow.inflow(lambda X: np.isclose(X[1], 0.0)) * args.mu_f * height / (dp * W), flow


(k_before, flow), (k_after, _) = permeability(preloaded), permeability(loaded)
# Kozeny-Carman falls by ~3 dn / n as the step compacts the column: c_v with the step's mean
k_eff = 0.5 * (k_before + k_after) if args.k_from == "mean" else k_before
c_v = k_eff / (args.mu_f * (1 / E_oed + porosity * FLUID.compressibility))
t_c = H0**2 / c_v

# ---- 3b. the drained modulus again, loaded as the saturated column's skeleton is --------
# slowly (a ramp over ~t_c) and without the damping of `hold`: a granular skeleton's
# settlement depends on how it is loaded (the damped step settles less)
if args.modulus == "ramped":
    E_damped, s_damped = E_oed, s_drained
    sim = column(preloaded)
    n_ramp = int(t_c / sim.dt) // 10
    for i in range(n_ramp):
        sim.set_external_force(np.arange(sim.p.n),
                               surcharge(args.preload + args.load * (i + 1) / n_ramp))
        sim.step(10)
    tail = []
    for i in range(n_ramp):
        sim.step(10)
        if i >= n_ramp // 2:
            tail.append(y0 - surface(sim))
    s_drained = float(np.mean(tail))
    u_dry = layer_settlement(sim.p.x[:, 1])
    E_oed = args.load * H0 / s_drained
    c_v = k_eff / (args.mu_f * (1 / E_oed + porosity * FLUID.compressibility))
    t_c = H0**2 / c_v
    log(f"ramped drained settlement {1e6 * s_drained:.2f} um (damped step "
        f"{1e6 * s_damped:.2f}): E_oed = {E_oed:.4g} Pa")
log(f"permeability {k_before:.4g} m^2 before the step, {k_after:.4g} after; used {k_eff:.4g} "
    f"m^2 (Kozeny-Carman, d = {1e3 * flow.d:.3f} mm): "
    f"c_v = {c_v:.4g} m^2/s, H^2 / c_v = {1e3 * t_c:.2f} ms, DEM dt = {sim.dt:.3g} s")

# ---- 4. consolidation: step load on the saturated column ------------------------------
sim = column(preloaded)
fluid = DarcyFlow(msh, sim, FLUID)
fluid.drained(lambda X: np.isclose(X[1], H_MESH))          # drained top, impermeable base
fluid.extra_force = surcharge(args.preload + args.load)
base = np.array([[W / 2, 0.0, 0.0]])
t, curve, profiles = 0.0, [], []
n_blocks = int(np.ceil(T_END * t_c / (args.every * sim.dt)))
for _ in range(n_blocks):
    fluid.step(args.every * sim.dt)
    sim.step(args.every, drag=fluid.drag)
    t += args.every * sim.dt
    curve.append((t, y0 - surface(sim), float(probe(fluid.p, base)[0, 0])))
    profiles.append(layer_settlement(sim.p.x[:, 1]))
wall_s = time.perf_counter() - t_start
t, s, p_base = np.array(curve).T

# ---- 5. against Terzaghi ----------------------------------------------------------------
m = 2 * np.arange(400) + 1


def degree_of_consolidation(tt):
    tt = np.atleast_1d(tt)
    return 1 - np.sum(8 / (m * np.pi) ** 2 * np.exp(-np.multiply.outer(tt, (m * np.pi) ** 2)
                                                    * c_v / (4 * H0**2)), axis=-1)


U_exact = degree_of_consolidation(t)
p_exact = terzaghi_pressure(H0, t, H=H0, p0=args.load, c=c_v) if np.ndim(t) == 0 else \
    np.array([terzaghi_pressure(H0, ti, H=H0, p0=args.load, c=c_v) for ti in t])
U = s / s_drained                 # against the dry drained settlement
U_final = s / s[-1]               # against the settlement reached (T_END: U_exact ~ 0.98)
late = t > 0.1 * t_c              # after the load's inertial start-up (H / wave speed)

# Terzaghi's pressure with the dry step's own strain profile: where the column is softer
# (near the loaded surface) it settles first, so its surface leads the uniform column's.
# u(z, t) = int_0^z du_dry/dz' (1 - p_T(z', t) / dq) dz', u_dry through the layers' means.
zc = 0.5 * (edges[1:] + edges[:-1])
zf = np.linspace(0, H0, 401)
du = np.gradient(np.interp(zf, np.r_[0, zc, H0], np.r_[0, u_dry, s_drained]), zf)


def profile_settlement(ti):
    load = du * (1 - terzaghi_pressure(H0 - zf, ti, H=H0, p0=args.load, c=c_v) / args.load)
    return np.r_[0, np.cumsum(0.5 * (load[1:] + load[:-1]) * np.diff(zf))]


U_profile = np.array([profile_settlement(ti)[-1] for ti in t]) / s_drained
strain_dry = np.diff(np.r_[0, u_dry, s_drained]) / np.diff(np.r_[0, zc, H0]) / (s_drained / H0)
errors_profile = float(np.abs(U - U_profile)[late].max())
errors = {"settlement_U_max_abs": float(np.abs(U - U_exact)[late].max()),
          "settlement_U_final_max_abs": float(np.abs(U_final * U_exact[-1] - U_exact)[late].max()),
          "base_pressure_max_abs_over_dq": float(np.abs(p_base - p_exact)[late].max()
                                                 / args.load),
          "final_U": float(U[-1]), "final_U_exact": float(U_exact[-1]),
          "settlement_U_vs_profile_terzaghi_max_abs": errors_profile}
T50 = float(np.interp(0.5, U_final * U_exact[-1], t) / t_c)
log(f"dry step's strain by layer (base to top) / mean: {np.round(strain_dry, 2)}; max |U - "
    f"U_Terzaghi with that profile| = {errors_profile:.3f}")
log(f"{len(t)} fluid steps ({len(t) * args.every} DEM steps) in {wall_s:.1f} s; final "
    f"settlement {U[-1]:.3f} x the dry drained one; after T = 0.1: max |U - U_Terzaghi| = "
    f"{errors['settlement_U_final_max_abs']:.3f} (U from the final settlement), "
    f"max |p_base - p_T| / dq = {errors['base_pressure_max_abs_over_dq']:.3f}; "
    f"T50 = {T50:.4f} (Terzaghi 0.1967)")

results = {
    "inputs": {"packing": args.packing, "width": W, "fill": args.fill, "r_min": args.r_min, "r_max": args.r_max,
               "kn": args.kn, "friction": MAT.friction, "wall_friction": WALLS.friction,
               "restitution": MAT.restitution,
               "density": MAT.density, "preload": args.preload, "load": args.load,
               "mu_f": args.mu_f, "beta_f": FLUID.compressibility, "rho_f": FLUID.density,
               "every": args.every, "porosity_space": FLUID.porosity_space,
               "T_end": T_END, "overconsolidate": args.overconsolidate,
               "headroom": args.headroom, "modulus": args.modulus, "seed": args.seed,
               "mesh": [1, args.rows],
               "loaded_grains": int(len(top)),
               "short": SHORT},
    "measured": {"modulus_from": args.modulus, "grains": int(p.n), "H": H0,
                 "porosity": porosity, "E_oed": E_oed, "s_drained": s_drained, "k": k_eff,
                 "k_before": k_before, "k_after": k_after, "c_v": c_v, "t_c": t_c,
                 "dem_dt": sim.dt},
    "dry_profile": {"layer_edges": edges.tolist(), "u_dry": u_dry.tolist(),
                    "strain_over_mean": strain_dry.tolist()},
    "errors": errors, "T50": T50, "T50_exact": 0.1967, "wall_s": wall_s,
    "curve": {"t": t.tolist(), "settlement": s.tolist(), "p_base": p_base.tolist(),
              "U_exact": U_exact.tolist(), "p_base_exact": p_exact.tolist(),
              "U_profile_terzaghi": U_profile.tolist(),
              "layers": np.array(profiles).tolist()},
}
args.out.mkdir(parents=True, exist_ok=True)
(args.out / "results.json").write_text(json.dumps(results, indent=1))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4.2))
ax1.plot(t / t_c, U, ".", ms=1, color="0.6", label="grains: s / s_drained (dry)")
ax1.plot(t / t_c, U_final * U_exact[-1], ".", ms=1, label="grains: s / s(T_end) x U(T_end)")
ax1.plot(t / t_c, U_exact, "k-", lw=1, label="Terzaghi (measured c_v)")
ax1.plot(t / t_c, U_profile, "k--", lw=1, label="Terzaghi, the dry step's strain profile")
ax1.set_xlabel("T = c_v t / H^2")
ax1.set_ylabel("degree of consolidation U")
ax1.legend(fontsize=8)
ax1.grid(alpha=0.3)
ax2.plot(t / t_c, p_base / args.load, ".", ms=1, label="base pore pressure")
ax2.plot(t / t_c, p_exact / args.load, "k-", lw=1, label="Terzaghi")
ax2.set_xlabel("T = c_v t / H^2")
ax2.set_ylabel("p / dq")
ax2.legend(fontsize=8)
ax2.grid(alpha=0.3)
fig.tight_layout()
fig.savefig(args.out / "grain_consolidation.png", dpi=120)

# ---- checks. Measured, full run, the lattice (350 grains): max |U - U_T| 0.041 against the
# dry step, 0.024 against the final settlement, base pressure 0.06 dq, final U 0.96; the
# random packing only within its path dependence (the docstring) ---
tol = 0.05 if args.packing == "lattice" else 0.35
assert errors["base_pressure_max_abs_over_dq"] < 0.2, errors
assert errors["settlement_U_max_abs"] < tol, errors
if not SHORT:     # the settlement's normalisation needs the end of consolidation
    assert errors["settlement_U_final_max_abs"] < tol, errors
    assert abs(errors["final_U"] - errors["final_U_exact"]) < tol, errors
