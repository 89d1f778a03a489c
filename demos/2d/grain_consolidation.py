"""Terzaghi consolidation of a column of grains in a Darcy pore fluid (seed 003).

This demo shows how to:

- settle a column of disks in a box, then preload it by a surcharge shared by its
  surface grains (no gravity from then on: a uniform preload, as in an oedometer),
- measure the column's drained oedometric modulus (a dry load step) and its permeability (a
  steady Darcy flow through it, :class:`coupling.pore_fluid.DarcyFlow`) on the same packing,
- load the saturated column by a step of the surcharge with a drained top and an
  impermeable base, the fluid's pressure solved every DEM step and handed to the grains,
- compare the settlement and the base pore pressure with Terzaghi's series solution for
  the measured c_v = k E_oed / mu_f,
- write ``results.json`` and ``grain_consolidation.png`` to ``--out``.

Run: ``python demos/2d/grain_consolidation.py`` (serial only: the DEM and the mesh are on
one rank); ``GRANFE_SHORT=1`` for a short run (to T = 0.5, ~25 s).
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

from coupling.pore_fluid import DarcyFlow, PoreFluidParameters, grain_volumes
from dem import ContactMaterial, Particles, Simulation, box_walls, relax
from dem.packing import random_packing
from granfe.consolidation import terzaghi_pressure
from granfe.probe import probe

SHORT = os.environ.get("GRANFE_SHORT") == "1"

# ---- parameters (SI) ------------------------------------------------------------------
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--width", type=float, default=0.04, help="column width W [m]")
parser.add_argument("--fill", type=float, default=0.04, help="height of the box filled [m]")
parser.add_argument("--r-min", type=float, default=0.9e-3, help="smallest radius [m]")
parser.add_argument("--r-max", type=float, default=1.1e-3, help="largest radius [m]")
parser.add_argument("--kn", type=float, default=2e4, help="normal contact stiffness [N/m]")
parser.add_argument("--preload", type=float, default=200.0, help="preload q0 [Pa]")
parser.add_argument("--load", type=float, default=200.0, help="load step dq [Pa]")
parser.add_argument("--mu-f", type=float, default=1e-3, help="fluid viscosity [Pa s]")
parser.add_argument("--every", type=int, default=1,
                    help="DEM steps per fluid step (explicit coupling: keep every * dt below "
                         "the drag time rho_s (1 - n) k / mu_f)")
parser.add_argument("--T-end", type=float, default=None, help="end time c_v t / H^2")
parser.add_argument("--rows", type=int, default=6, help="mesh rows (one column of quads)")
parser.add_argument("--porosity-space", default="P1", help="DG0 or P1 (see coupling.pore_fluid)")
parser.add_argument("--seed", type=int, default=3)
parser.add_argument("--out", type=Path, default=Path("output/grain_consolidation"))
args = parser.parse_args()
comm = MPI.COMM_SELF            # the DEM is serial here; the fluid solve too
T_END = args.T_end or (0.5 if SHORT else 1.5)
MAT = ContactMaterial(E=1e7, nu=0.25, density=2650.0, friction=0.3, restitution=0.3,
                      law="linear", kn=args.kn, kt=0.5 * args.kn)
FLUID = PoreFluidParameters(viscosity=args.mu_f, porosity_space=args.porosity_space)
W = args.width


def log(msg):
    if MPI.COMM_WORLD.rank == 0:
        print(msg, flush=True)


def column(state=None):
    """The settled column as a fresh Simulation without gravity (from ``state`` if given):
    a floor and two side walls, no lid; the load is a surcharge on the top grains."""
    p = Particles.spheres(packed[0], packed[1], MAT.density, dim=2)
    sim = Simulation(p, MAT, walls=box_walls([0, 0, 0], [W, 1, 0], dim=2), safety=0.1,
                     allow_overlap=True)
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
x, r = random_packing([0, 0], [W, args.fill], args.r_min, args.r_max, 0.45, seed=args.seed,
                      strict=False)
p = Particles.spheres(x, r, MAT.density, dim=2)
sim = Simulation(p, MAT, walls=box_walls([0, 0, 0], [W, 1, 0], dim=2), gravity=(0, -9.81),
                 safety=0.1)
relax(sim, tol=1e-3, check_every=200)
packed = (p.x.copy(), p.radius.copy())
top = top_grains(*packed)
sim = column()
hold(sim, args.preload)
preloaded = sim.state_dict()
H0 = float((sim.p.x[:, 1] + sim.p.radius).max())     # the column's height
H_MESH = H0 + 2 * args.r_max      # drained top a grain above: surface grains may rise
y0 = surface(sim)
V = grain_volumes(p.radius, 2)
porosity = 1 - V.sum() / (W * H0)
log(f"{p.n} grains ({len(top)} loaded), column H = {1e3 * H0:.2f} mm, porosity {porosity:.4f}")

# ---- 2. drained oedometric modulus: a dry load step -----------------------------------
sim = column(preloaded)
hold(sim, args.preload + args.load)
s_drained = y0 - surface(sim)
E_oed = args.load * H0 / s_drained
log(f"drained settlement {1e6 * s_drained:.2f} um: E_oed = {E_oed:.4g} Pa")

# ---- 3. permeability: steady upward flow through the preloaded column -----------------
sim = column(preloaded)
# a 1D problem: full-width rows of ~30 grains each (the porosity's averaging volume)
msh = mesh.create_rectangle(comm, [[0, 0], [W, H_MESH]], [1, args.rows],
                            mesh.CellType.quadrilateral)
flow = DarcyFlow(msh, sim, PoreFluidParameters(viscosity=args.mu_f, compressibility=0.0,
                                                porosity_space=args.porosity_space))
dp = 10.0
flow.pressure(lambda X: np.isclose(X[1], 0.0), dp)
flow.drained(lambda X: np.isclose(X[1], H_MESH))
flow.solve()
k_eff = flow.inflow(lambda X: np.isclose(X[1], 0.0)) * args.mu_f * H0 / (dp * W)
c_v = k_eff / (args.mu_f * (1 / E_oed + porosity * FLUID.compressibility))
t_c = H0**2 / c_v
log(f"permeability {k_eff:.4g} m^2 (Kozeny-Carman, d = {1e3 * flow.d:.3f} mm): "
    f"c_v = {c_v:.4g} m^2/s, H^2 / c_v = {1e3 * t_c:.2f} ms, DEM dt = {sim.dt:.3g} s")

# ---- 4. consolidation: step load on the saturated column ------------------------------
sim = column(preloaded)
fluid = DarcyFlow(msh, sim, FLUID)
fluid.drained(lambda X: np.isclose(X[1], H_MESH))          # drained top, impermeable base
fluid.extra_force = surcharge(args.preload + args.load)
base = np.array([[W / 2, 0.0, 0.0]])
t, curve = 0.0, []
n_blocks = int(np.ceil(T_END * t_c / (args.every * sim.dt)))
for _ in range(n_blocks):
    fluid.step(args.every * sim.dt)
    sim.step(args.every)
    t += args.every * sim.dt
    curve.append((t, y0 - surface(sim), float(probe(fluid.p, base)[0, 0])))
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
errors = {"settlement_U_max_abs": float(np.abs(U - U_exact)[late].max()),
          "settlement_U_final_max_abs": float(np.abs(U_final * U_exact[-1] - U_exact)[late].max()),
          "base_pressure_max_abs_over_dq": float(np.abs(p_base - p_exact)[late].max()
                                                 / args.load),
          "final_U": float(U[-1]), "final_U_exact": float(U_exact[-1])}
T50 = float(np.interp(0.5, U_final * U_exact[-1], t) / t_c)
log(f"{len(t)} fluid steps ({len(t) * args.every} DEM steps) in {wall_s:.1f} s; final "
    f"settlement {U[-1]:.3f} x the dry drained one; after T = 0.1: max |U - U_Terzaghi| = "
    f"{errors['settlement_U_final_max_abs']:.3f} (U from the final settlement), "
    f"max |p_base - p_T| / dq = {errors['base_pressure_max_abs_over_dq']:.3f}; "
    f"T50 = {T50:.4f} (Terzaghi 0.1967)")

results = {
    "inputs": {"width": W, "fill": args.fill, "r_min": args.r_min, "r_max": args.r_max,
               "kn": args.kn, "friction": MAT.friction, "restitution": MAT.restitution,
               "density": MAT.density, "preload": args.preload, "load": args.load,
               "mu_f": args.mu_f, "beta_f": FLUID.compressibility, "rho_f": FLUID.density,
               "every": args.every, "T_end": T_END, "seed": args.seed, "mesh": [1, args.rows],
               "loaded_grains": int(len(top)),
               "short": SHORT},
    "measured": {"grains": int(p.n), "H": H0, "porosity": porosity, "E_oed": E_oed,
                 "s_drained": s_drained, "k": k_eff, "c_v": c_v, "t_c": t_c, "dem_dt": sim.dt},
    "errors": errors, "T50": T50, "T50_exact": 0.1967, "wall_s": wall_s,
    "curve": {"t": t.tolist(), "settlement": s.tolist(), "p_base": p_base.tolist(),
              "U_exact": U_exact.tolist(), "p_base_exact": p_exact.tolist()},
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

# ---- checks (a few hundred grains, one packing; the full run measured 0.106 and 0.142) ---
assert errors["base_pressure_max_abs_over_dq"] < 0.15, errors
if not SHORT:     # the settlement's normalisation needs the end of consolidation
    assert errors["settlement_U_final_max_abs"] < 0.2, errors
    assert 0.9 < errors["final_U"] < 1.25, errors
