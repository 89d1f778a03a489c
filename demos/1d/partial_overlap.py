"""Partial overlap of a glued sphere string and a micropolar rod (seed 001 §2.4.4, Fig. 11-13).

This demo shows how to:

- overlap an 11-sphere glued Hertz-Mindlin string (centres 0..10 cm) with a 4-element
  micropolar rod on [4, 20] cm: the cell [4, 8] cm lies under the particles (B^h^), the
  cell [8, 12] cm holds the string's end (B^h~, 2.5 particle volumes: volume fraction
  ``q^ = (h A - 2.5 (4/3) pi R^3) / (h A) = 0.583``), the rest is FE only,
- prescribe the FE dofs under the particles by the L2 projection of the particle motion
  and solve eq. 125-126 for the free particle and free nodal dofs by Newton,
- compare unscaled (g = 1) and scaled (g = (0.0195, 0.8, 0.85)) rods (Fig. 12) and the
  rotational energy factoring q^theta = 0.9 (Fig. 13) that calms the particle rotations.

Loads: axial 10 kN at particle 1 (x = 0) first, then transverse 10 kN; the rod is
clamped at x = 20 cm. Serial model; under MPI every rank computes, rank 0 writes.

Run: ``python demos/1d/partial_overlap.py [--out DIR]``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np

from coupling.monolithic1d import partial_overlap
from dem.glued import GluedLaw, GluedString
from granfe.materials import MicropolarMaterial
from granfe.rod1d import Rod1D

parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--out", type=Path, default=Path("output/partial_overlap"))
args = parser.parse_args()
comm = MPI.COMM_WORLD

# ---- parameters (SI), seed 001 §2.4.3-2.4.4 ---------------------------------------------
n_spheres, R = 11, 0.005  # spheres, radius [m]
n_elements, x_rod, L = 4, 0.04, 0.16  # rod elements, left end [m], length [m]
E, nu, B_factor, ell = 29e9, 0.25, 50.0, 0.01  # as in §2.4.3
F = 1e4  # axial then transverse force at particle 1 [N]
A, I = np.pi * R**2, np.pi * R**4 / 4
h = L / n_elements
q_hat = (h * A - 2.5 * 4 / 3 * np.pi * R**3) / (h * A)  # seed: 0.583
runs = {  # name: (g^u, g^v, g^theta), (q^u, q^v, q^theta)
    "fig12_not_scaled": ((1.0, 1.0, 1.0), (0.0, 0.0, 0.0)),
    "fig12_scaled": ((0.0195, 0.8, 0.85), (0.0, 0.0, 0.0)),
    "fig13_rotation_factored": ((0.0195, 0.8, 0.85), (0.0, 0.0, 0.9)),
}
material = MicropolarMaterial.from_engineering(E, nu, length=ell, kappa_over_mu=0.1,
                                               gamma_over_l2mu=400.0)
string = GluedString(n_spheres, GluedLaw(E, nu, R, B_factor))

# ---- solve ----------------------------------------------------------------------------------
results = {}
for name, (g, q) in runs.items():
    rod = Rod1D(material, L, A, I, n_elements, MPI.COMM_SELF, scaling=g, x0=x_rod)
    c = partial_overlap(string, rod, q_hat, q)
    X = np.zeros(c.n)
    X[:string.n_dofs] = string.axial_predictor(F)
    f = np.zeros(c.n)
    hist = []
    for dof in (0, 1):  # axial, then transverse with the axial held
        f[dof] = F
        X, rep = c.solve(f, X)
        hist += rep.history
    clamp = rod.end_dofs("right")
    reaction = (rod.K @ (c.T @ X))[clamp]  # rod weights are 1 at the clamp cell
    theta = np.array(c.fields(X)["particles"]["theta"])
    results[name] = c.fields(X) | {
        "g": g, "q": q, "newton_history": hist,
        "end_force_split": {"applied_at_particle_1": [F, F],
                            "clamp_reaction": reaction[:2].tolist()},
        "particle_rotation_oscillation": float(np.abs(np.diff(theta)).max())}

# ---- Fig. 12 against the seed: axial gradients in closed form -------------------------------
# The seed's text: with g^u = 0.0195 "we can achieve a homogeneous axial displacement gradient
# across the overlap". Statics puts the same axial force F through every contact and every
# FE section, so both gradients are closed forms of the printed parameters.
m = material
C = m.lam + 2 * m.mu + m.kappa
de_strain = (F / string.law.k_hertz) ** (2 / 3) / (2 * R)  # eq. 60: delta_n / (2 R)
r = results["fig12_scaled"]
xu, uu = np.array(r["nodes"]["u"]["x"]), np.array(r["nodes"]["u"]["value"])
xp, up = np.array(r["particles"]["x"]), np.array(r["particles"]["u"])
fe_only = xu >= x_rod + 2 * h - 1e-12
g_u = runs["fig12_scaled"][0][0]
seed_fig12 = {
    "seed_text": "homogeneous axial displacement gradient across the overlap with g^u = 0.0195 "
                 "(Fig. 12, image not in the OCR)",
    "de_strain_closed_form": de_strain,
    "de_strain_computed": float(-np.polyfit(xp[xp < x_rod], up[xp < x_rod], 1)[0]),
    "fe_strain_closed_form": F / (g_u * C * A),
    "fe_strain_computed": float(-np.polyfit(xu[fe_only], uu[fe_only], 1)[0]),
    "fe_over_de_strain": F / (g_u * C * A) / de_strain,
    "g_u_that_would_match": F / (C * A * de_strain),
    "why": "Same spheres, law and 10 kN as Fig. 8, where the seed (and we) match the axial "
           "tip with g^u = 0.077; a homogeneous gradient needs that g^u again. The printed "
           "0.0195 = 0.077 / 3.95 makes the FE-only cells ~4x more strained than the string: "
           "the seed's two examples disagree with each other by this factor (a cross-section "
           "area from the diameter, pi d^2 = 4 pi R^2, in one of them would give exactly 4). "
           "Not a path of ours: both computed gradients equal their closed forms.",
}

# ---- output ---------------------------------------------------------------------------------
if comm.rank == 0:
    args.out.mkdir(parents=True, exist_ok=True)
    results["seed_fig12_comparison"] = seed_fig12
    results["inputs"] = {"n_spheres": n_spheres, "R": R, "n_elements": n_elements,
                         "x_rod": x_rod, "L": L, "E": E, "nu": nu, "B": B_factor, "l": ell,
                         "q_hat": q_hat, "F": F}
    (args.out / "results.json").write_text(json.dumps(results, indent=2))

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(len(runs), 3, figsize=(13, 3.2 * len(runs)))
    for i, key in enumerate(runs):
        r = results[key]
        for j, (fld, unit, s) in enumerate((("u", "cm", 100), ("v", "cm", 100), ("theta", "rad", 1))):
            ax[i, j].plot(100 * np.array(r["particles"]["x"]), s * np.array(r["particles"][fld]),
                          "o", ms=4, label="particle centroids")
            ax[i, j].plot(100 * np.array(r["nodes"][fld]["x"]),
                          s * np.array(r["nodes"][fld]["value"]), "s-", ms=4,
                          label="finite element nodes")
            for xb in (x_rod, x_rod + h, x_rod + 2 * h):
                ax[i, j].axvline(100 * xb, color="0.8", lw=0.8)
            ax[i, j].set(xlabel="x (cm)", ylabel=f"{fld} ({unit})", title=f"{key}: {fld}")
        ax[i, 0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "partial_overlap.png", dpi=110)
    print(f"axial strain: string {de_strain:.4f}, FE-only cells "
          f"{seed_fig12['fe_strain_computed']:.4f} ({seed_fig12['fe_over_de_strain']:.2f}x); "
          f"g^u {seed_fig12['g_u_that_would_match']:.4f} would match")
    print(f"q_hat = {q_hat:.3f}; rotation oscillation (max |dtheta|): "
          + ", ".join(f"{k} {v['particle_rotation_oscillation']:.2e}" for k, v in results.items()
                      if k in runs))

# ---- checks ---------------------------------------------------------------------------------
assert abs(q_hat - 0.583) < 1e-3
assert abs(seed_fig12["de_strain_computed"] / de_strain - 1) < 1e-6, "DE gradient = closed form"
assert abs(seed_fig12["fe_strain_computed"] * g_u * C * A / F - 1) < 1e-6, "FE = closed form"
for key in runs:
    assert np.allclose(results[key]["end_force_split"]["clamp_reaction"], [-F, -F], rtol=1e-8)
assert (results["fig13_rotation_factored"]["particle_rotation_oscillation"]
        < 0.5 * results["fig12_scaled"]["particle_rotation_oscillation"])
