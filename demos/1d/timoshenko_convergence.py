"""Convergence of the 1D micropolar Timoshenko rod (seed 001 §2.2.4, Fig. 4).

This demo shows how to:

- build the mixed (u P1, v P2, theta P1) micropolar rod of seed 001 eq. 39-57 on an
  interval mesh (distributed over MPI ranks) and solve a cantilever with end loads,
- check the axial tip displacement against ``F L / ((lam + 2 mu + kappa) A)`` (exact on
  every mesh) and the transverse tip against the closed form of the seed's equations
  ``v = kappa/(mu + kappa) F L^3 / (3 B) + F L / ((mu + kappa) A)``, ``B = C I + gamma A``,
- measure the observed convergence rate and plot force against tip displacement as in
  seed Fig. 4 (2, 5, 10, 20 elements).

Run: ``mpiexec -n 2 python demos/1d/timoshenko_convergence.py [--out DIR]``.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np

from granfe.materials import MicropolarMaterial
from granfe.rod1d import Rod1D, cantilever_tip

SHORT = os.environ.get("GRANFE_SHORT") == "1"

# ---- parameters (SI), seed 001 §2.2.4 --------------------------------------------------
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--out", type=Path, default=Path("output/timoshenko_convergence"))
parser.add_argument("--formulation", choices=("seed", "energy"), default="seed")
args = parser.parse_args()
comm = MPI.COMM_WORLD

L = 0.20  # rod length [m]
R = 0.005  # circular section radius [m]
E, nu = 10e9, 0.3  # Young's modulus [Pa], Poisson's ratio
ell = 0.01  # characteristic length [m]
F = (1e3, 1e3, 0.0)  # end loads at x = 0: axial [N], transverse [N], moment [N m]
meshes = [2, 5, 10, 20] if not SHORT else [2, 5]
A, I = np.pi * R**2, np.pi * R**4 / 4
material = MicropolarMaterial.from_engineering(E, nu, length=ell, kappa_over_mu=0.1,
                                               gamma_over_l2mu=0.05)

# ---- solve: cantilever clamped at x = L, loaded at x = 0 ---------------------------------
u_exact, v_exact = cantilever_tip(material, L, A, I, F[:2], args.formulation)
runs = []
for n in meshes + [2 * meshes[-1], 4 * meshes[-1]]:
    rod = Rod1D(material, L, A, I, n, comm, formulation=args.formulation)
    u, v, th = rod.solve(F, clamp="right").at(0.0, comm)
    runs.append({"n_elements": n, "axial_tip_displacement": float(u),
                 "transverse_tip_displacement": float(v),
                 "tip_rotation": float(th)})
err = np.array([v_exact - r["transverse_tip_displacement"] for r in runs])
h = L / np.array([r["n_elements"] for r in runs])
rates = np.log(err[:-1] / err[1:]) / np.log(h[:-1] / h[1:])

# ---- output ---------------------------------------------------------------------------------
if comm.rank == 0:
    args.out.mkdir(parents=True, exist_ok=True)
    results = {
        "inputs": {"L": L, "R": R, "E": E, "nu": nu, "kappa_over_mu": 0.1,
                   "gamma_over_l2mu": 0.05, "l": ell, "A": A, "I": I, "end_loads": F,
                   "formulation": args.formulation, "ranks": comm.size},
        "axial_tip_displacement_exact": u_exact,
        "transverse_tip_displacement_exact": v_exact,
        "meshes": runs,
        "transverse_error": err.tolist(),
        "observed_rates": rates.tolist(),
    }
    (args.out / "results.json").write_text(json.dumps(results, indent=2))

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8))
    lam = np.linspace(0, 1, 11)
    for r in runs[:len(meshes)]:
        lab = f"{r['n_elements']} elements"
        ax[0].plot(100 * lam * r["axial_tip_displacement"], lam, label=lab)
        ax[1].plot(100 * lam * r["transverse_tip_displacement"], lam, label=lab)
    ax[0].set(xlabel="axial displacement of node 1 (cm)", ylabel="FORCE (kN)",
              title="f_x vs d_x of node 1")
    ax[1].set(xlabel="transverse displacement of node 1 (cm)", title="f_y vs d_y of node 1")
    ax[1].axvline(100 * v_exact, color="k", ls=":", label="closed form")
    ax[1].legend(fontsize=8)
    ax[2].loglog(h, np.abs(err), "o-", label=f"rate {rates[-1]:.2f}")
    ax[2].set(xlabel="h (m)", ylabel="|v - v_exact| (m)", title="transverse tip error")
    ax[2].legend()
    fig.tight_layout()
    fig.savefig(args.out / "force_displacement.png", dpi=120)
    print(f"u_tip = {runs[0]['axial_tip_displacement']:.6e} m (exact {u_exact:.6e}); "
          f"v_tip = {[round(r['transverse_tip_displacement'], 6) for r in runs]} m "
          f"(exact {v_exact:.6e}); rates {np.round(rates, 2).tolist()}")

# ---- checks ---------------------------------------------------------------------------------
for r in runs:
    assert abs(r["axial_tip_displacement"] - u_exact) < 1e-12 * u_exact
assert np.all(err > 0) and np.all(np.diff(err) < 0), "transverse tip must converge monotonically"
assert rates[-1] > 1.8, f"observed rate {rates[-1]} below 2"
