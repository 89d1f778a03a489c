"""Size effect in a sheared micromorphic layer (plane strain, small strain).

This demo shows how to:

- set up the small-strain Eringen-Mindlin micromorphic continuum (u and the 2x2
  micro-displacement phi = chi - I) with :class:`granfe.models.micromorphic.Micromorphic`,
- solve a layer of height H sheared between two plates that also hold the micro-structure
  (u = (delta, 0) and phi = 0 on top, u = 0 and phi = 0 at the bottom),
- compare the FE field with the exact solution of the layer (fields of y only: a linear ODE
  system solved by transfer matrices, to round-off) on two meshes,
- measure the size effect: the apparent shear modulus ``G_app = sigma_xy H / delta``
  falls from ``G_0`` (thin layer, phi held at zero) to ``G_eff`` (thick layer, phi relaxed)
  with H over the length scale l of the moduli of grad chi.

The side walls carry the exact solution as Dirichlet data, so the FE solution is the layer's.
Run: ``mpiexec -n 2 python demos/2d/micromorphic_shear_layer.py [--height-over-length 4 ...]``.
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
from scipy import sparse
from scipy.linalg import expm
from scipy.sparse.linalg import spsolve

from granfe.io import ContinuumWriter
from granfe.models.micromorphic import (
    Micromorphic,
    MicromorphicMaterial,
    micromorphic_energy,
    micromorphic_stresses,
)
from granfe.probe import probe
from granfe.problem import ContinuumProblem

SHORT = os.environ.get("GRANFE_SHORT") == "1"

# ---- parameters (SI) ------------------------------------------------------------------
parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--modulus", type=float, default=1.0e8, help="modulus scale mu_0 [Pa]")
parser.add_argument("--length", type=float, default=1.0e-3,
                    help="length scale l [m]: the moduli of grad chi are (ratios) * mu_0 l^2")
parser.add_argument("--height-over-length", type=float, default=4.0, help="H / l of the FE layer")
parser.add_argument("--shear", type=float, default=1.0e-3, help="nominal shear strain delta / H")
parser.add_argument("--cells", type=int, nargs=2, default=(8, 16),
                    help="cells across the height of the two FE meshes")
parser.add_argument("--out", type=Path, default=Path("output/micromorphic_shear_layer"))
args = parser.parse_args()
comm = MPI.COMM_WORLD

mu0, ell = args.modulus, args.length
# moduli over mu_0 (A, B, D) and over mu_0 l^2 (C): a positive-definite set
RATIOS = dict(lam=2.0, mu=1.0, eta=0.5, tau=0.2, kappa=1.5, nu=0.3, sigma=0.1)
TAU_RATIOS = (0.1, 0.05, 0.2, 0.15, 0.05, 0.1, 1.0, 0.2, 0.1, 0.15, 0.05)
material = MicromorphicMaterial(**{k: v * mu0 for k, v in RATIOS.items()},
                                **{f"tau{i + 1}": t * mu0 * ell**2 for i, t in enumerate(TAU_RATIOS)})
H = args.height_over_length * ell
delta = args.shear * H
cells = (4, 8) if SHORT else tuple(args.cells)


# ---- the exact layer solution -------------------------------------------------------------
def layer_matrices(mat):
    """Hessian Q of W(w', w) for fields of y only, w = (u_x, u_y, phi_xx, phi_xy, phi_yx,
    phi_yy), and the first-order system ``Z' = M Z``, ``Z = (w, w')`` of its Euler-Lagrange
    equations ``d/dy (Q_pp w' + Q_pw w) = Q_wp w' + Q_ww w``."""
    def energy(z):
        p, w = z[:6], z[6:]
        grad_u = np.array([[0.0, p[0]], [0.0, p[1]]])
        grad_chi = np.zeros((2, 2, 2))
        grad_chi[:, :, 1] = p[2:].reshape(2, 2)
        return micromorphic_energy(grad_u, np.eye(2) + w[2:].reshape(2, 2), grad_chi, mat)

    e = np.eye(12)
    Q = np.array([[energy(e[a] + e[b]) - energy(e[a]) - energy(e[b]) for b in range(12)]
                  for a in range(12)])
    Qpp, Qpw, Qwp, Qww = Q[:6, :6], Q[:6, 6:], Q[6:, :6], Q[6:, 6:]
    M = np.zeros((12, 12))
    M[:6, 6:] = np.eye(6)
    M[6:, :6] = np.linalg.solve(Qpp, Qww)
    M[6:, 6:] = np.linalg.solve(Qpp, Qwp - Qpw)
    return M


def layer_solution(M, height, top, segments=None):
    """Exact layer of the system ``M`` (:func:`layer_matrices`): ``Z(y)`` for w(0) = 0,
    w(H) = top, by transfer matrices over segments no longer than l/2 (one shooting over a
    thick layer would lose all digits to exp(H/l))."""
    n = segments or max(4, int(np.ceil(2 * height / ell)))
    h = height / n
    E = expm(M * h)
    A = sparse.lil_matrix((12 * (n + 1), 12 * (n + 1)))
    rhs = np.zeros(12 * (n + 1))
    for k in range(n):          # Z_{k+1} - E Z_k = 0
        A[12 * k:12 * k + 12, 12 * k:12 * k + 12] = -E
        A[12 * k:12 * k + 12, 12 * k + 12:12 * k + 24] = np.eye(12)
    A[12 * n:12 * n + 6, :6] = np.eye(6)                      # w(0) = 0
    A[12 * n + 6:, 12 * n:12 * n + 6] = np.eye(6)             # w(H) = top
    rhs[12 * n + 6:] = top
    Z = spsolve(A.tocsc(), rhs).reshape(n + 1, 12)

    def at(y):
        y, inverse = np.unique(np.atleast_1d(np.asarray(y, dtype=float)), return_inverse=True)
        k = np.clip((y // h).astype(int), 0, n - 1)
        Zy = np.array([expm(M * (yi - k_ * h)) @ Z[k_] for yi, k_ in zip(y, k, strict=True)])
        return Zy[inverse.reshape(-1)]
    return at


def shear_stress(mat, Z):
    """sigma_xy (constant through the layer) from a layer state Z = (w, w')."""
    w, p = Z[:6], Z[6:]
    grad_chi = np.zeros((2, 2, 2))
    grad_chi[:, :, 1] = p[2:].reshape(2, 2)
    sigma, _, _ = micromorphic_stresses(np.array([[0.0, p[0]], [0.0, p[1]]]),
                                        np.eye(2) + w[2:].reshape(2, 2), grad_chi, mat)
    return sigma[0, 1]


def bounds(mat, gamma=1.0):
    """G_0 (phi = 0) and G_eff (phi relaxed, u_y' = 0) of homogeneous simple shear."""
    grad_u = np.array([[0.0, gamma], [0.0, 0.0]])
    zero = np.zeros((2, 2, 2))
    G0 = 2 * micromorphic_energy(grad_u, np.eye(2), zero, mat) / gamma**2

    def residual(phi):       # s - sigma, affine in phi
        sig, s, _ = micromorphic_stresses(grad_u, np.eye(2) + phi.reshape(2, 2), zero, mat)
        return (s - sig).reshape(-1)

    r0 = residual(np.zeros(4))
    J = np.column_stack([residual(e) - r0 for e in np.eye(4)])
    phi = np.linalg.solve(J, -r0)
    return G0, 2 * micromorphic_energy(grad_u, np.eye(2) + phi.reshape(2, 2), zero, mat) / gamma**2


top = np.array([delta, 0.0, 0.0, 0.0, 0.0, 0.0])
M_layer = layer_matrices(material)
exact = layer_solution(M_layer, H, top)
tau_exact = shear_stress(material, exact(H)[0])
G0, G_eff = bounds(material)

# ---- FE on two meshes -------------------------------------------------------------------
L = H / 2
ys = np.linspace(0.0, H, 41)
line = np.column_stack([np.full_like(ys, L / 2), ys, np.zeros_like(ys)])
Z_line = exact(ys)
runs = []
for ny in cells:
    t0 = time.perf_counter()
    domain = mesh.create_rectangle(comm, [[0.0, 0.0], [L, H]], [max(ny // 2, 1), ny])
    problem = ContinuumProblem(domain, Micromorphic(material), prefix=f"layer{ny}_")
    wall = lambda x: np.isclose(x[0], 0.0) | np.isclose(x[0], L) | np.isclose(x[1], 0.0) | np.isclose(x[1], H)  # noqa: E731
    problem.fix(wall, "u", lambda x: exact(x[1])[:, :2].T.copy())
    problem.fix(wall, "phi", lambda x: exact(x[1])[:, 2:6].T.copy())
    problem.solve()
    u_h = probe(problem.w.sub(0).collapse(), line)
    phi_h = probe(problem.w.sub(1).collapse(), line)
    reaction = problem.reaction(lambda x: np.isclose(x[1], H), "u_x")
    runs.append({
        "cells_across": ny,
        "dofs": int(problem.V.dofmap.index_map.size_global * problem.V.dofmap.index_map_bs),
        "max_error_u_over_delta": float(np.abs(u_h - Z_line[:, :2]).max() / delta),
        "max_error_phi_over_max_phi": float(np.abs(phi_h - Z_line[:, 2:6]).max()
                                            / np.abs(Z_line[:, 2:6]).max()),
        "top_reaction_x_per_length": reaction / L,
        "time_s": time.perf_counter() - t0,
    })
rates = {k: float(np.log2(runs[0][k] / runs[1][k]))
         for k in ("max_error_u_over_delta", "max_error_phi_over_max_phi")}
writer = ContinuumWriter(problem, args.out, name="micromorphic_shear_layer")
writer.write(0.0)
writer.close()

# ---- size effect (exact layer solutions) -----------------------------------------------------
h_over_l = np.geomspace(0.25, 200.0, 16 if SHORT else 40)
G_app = np.array([shear_stress(material, layer_solution(M_layer, r * ell, top * r * ell / H)(r * ell)[0])
                  / args.shear for r in h_over_l])

results = {
    "inputs": {"modulus_mu0": mu0, "length_l": ell, "height_H": H, "width_L": L,
               "shear_delta_over_H": args.shear, "cells": list(cells), "degree": [2, 1],
               "moduli": material.moduli(), "short": SHORT, "ranks": comm.size},
    "exact_shear_stress_sigma_xy": tau_exact,
    "G_app_over_G_eff_at_H": tau_exact / args.shear / G_eff,
    "G0": G0, "G_eff": G_eff,
    "fe": runs, "fe_rates": rates,
    "size_effect": {"H_over_l": h_over_l.tolist(), "G_app_over_G_eff": (G_app / G_eff).tolist()},
    "references": ["Eringen 1999, Microcontinuum Field Theories I (isotropic moduli)",
                   "Regueiro 2010, On finite strain micromorphic elastoplasticity, IJSS "
                   "(deformation measures, linearised here)",
                   "Tardigrade micromorphic_linear_elasticity (UCBoulder), formIsotropicA..D",
                   "Smith 1968 (positive-definiteness conditions; Tardigrade's constraint "
                   "equations)"],
}

# ---- figures --------------------------------------------------------------------------------
if comm.rank == 0:
    import matplotlib.pyplot as plt

    args.out.mkdir(parents=True, exist_ok=True)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    yy = np.linspace(0.0, H, 201)
    Zf = exact(yy)
    ax1.plot(Zf[:, 0] / delta, yy / H, "k-", label="u_x / delta (exact)")
    ax1.plot(u_h[::2, 0] / delta, ys[::2] / H, "ko", mfc="none", label="FE")
    for j, name in ((3, "phi_xy"), (4, "phi_yx"), (2, "phi_xx")):
        ax1.plot(Zf[:, j] / args.shear, yy / H, label=f"{name} / (delta/H)")
        ax1.plot(phi_h[::2, j - 2] / args.shear, ys[::2] / H, "o", mfc="none", color="gray")
    ax1.set_ylabel("y / H")
    ax1.legend(fontsize=8)
    ax1.set_title(f"H / l = {args.height_over_length:g}")
    ax2.semilogx(h_over_l, G_app / G_eff, "k-", label="G_app / G_eff")
    ax2.axhline(G0 / G_eff, color="r", ls=":", label="G_0 / G_eff (phi = 0)")
    ax2.axhline(1.0, color="b", ls=":", label="1 (phi relaxed)")
    ax2.set_xlabel("H / l")
    ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "shear_layer.png", dpi=120)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    for r in runs:
        print(f"ny = {r['cells_across']:3d}: dofs {r['dofs']}, max |u_h - u| / delta "
              f"{r['max_error_u_over_delta']:.2e}, max |phi_h - phi| / max|phi| "
              f"{r['max_error_phi_over_max_phi']:.2e}, top reaction / L "
              f"{r['top_reaction_x_per_length']:.6g} Pa (exact sigma_xy {tau_exact:.6g})")
    print(f"rates {rates}; G_0 / G_eff = {G0 / G_eff:.4f}; G_app / G_eff at H / l = "
          f"{args.height_over_length:g}: {tau_exact / args.shear / G_eff:.4f}; outputs in {args.out}")

# ---- checks ---------------------------------------------------------------------------------
# FE = exact layer up to the discretisation error, which falls at least like h^2 (u) and h (phi)
# (measured at H / l = 4: ny = 8: 2.6e-4, 2.3e-2, 1.2 %; ny = 16: 5.1e-5, 6.3e-3, 0.3 %)
coarse = 4 if SHORT else 1
assert runs[-1]["max_error_u_over_delta"] < 1e-4 * coarse
assert runs[-1]["max_error_phi_over_max_phi"] < 1e-2 * coarse
assert rates["max_error_u_over_delta"] > 1.8 and rates["max_error_phi_over_max_phi"] > 0.9
assert abs(runs[-1]["top_reaction_x_per_length"] - tau_exact) < 5e-3 * coarse * abs(tau_exact)
# sigma_xy is uniform through the exact layer (d sigma_xy / dy = 0)
taus = [shear_stress(material, Z) for Z in Z_line]
assert np.ptp(taus) < 1e-9 * abs(tau_exact)
# size effect: monotone from G_0 (thin) to G_eff (thick)
assert G0 > G_eff and np.all(np.diff(G_app) < 0)
assert abs(G_app[0] / G0 - 1) < 0.05 and abs(G_app[-1] / G_eff - 1) < 0.05
