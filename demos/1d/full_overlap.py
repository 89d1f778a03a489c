"""Full overlap of a glued sphere string and a micropolar rod (seed 001 §2.4.3, Fig. 7-10).

This demo shows how to:

- build the 21-sphere glued Hertz-Mindlin string (:mod:`dem.glued`) and the 5-element
  scaled micropolar rod (:mod:`granfe.rod1d`) over the same 20 cm,
- solve them uncoupled (Fig. 8), and coupled by eq. 122
  ``(1 - q) F^DE(Q) + q B^T K (B Q) = F^EXT`` with ``B = M^-1 N^T`` with energy factors
  q = (0.65, 0.5, 0.5) (Fig. 9) and q = 0 (Fig. 10), by Newton with line search,
- split the force at particle 1 into its DE and projected-FE parts (Fig. 9: ~6.3 kN +
  ~3.6 kN = 10 kN) and plot displacements and rotations along x for particles and nodes.

Loads: axial 10 kN at particle 1 (x = 0) first, then transverse 10 kN with the axial
held; cantilevered at x = L. Serial model (tiny dense systems): under MPI every rank
computes the same thing and rank 0 writes.

Run: ``python demos/1d/full_overlap.py [--out DIR]``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np

from coupling.monolithic1d import full_overlap
from dem.glued import GluedLaw, GluedString
from granfe.materials import MicropolarMaterial
from granfe.rod1d import Rod1D

parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
parser.add_argument("--out", type=Path, default=Path("output/full_overlap"))
args = parser.parse_args()
comm = MPI.COMM_WORLD

# ---- parameters (SI), seed 001 §2.4.3 --------------------------------------------------
n_spheres, R = 21, 0.005  # spheres, radius [m] (1 cm diameter)
n_elements, L = 5, 0.20  # rod elements, length [m]
E, nu, B_factor = 29e9, 0.25, 50.0  # Young's modulus [Pa], Poisson's ratio, contact B
ell = 0.01  # characteristic length [m]; kappa = 0.1 mu, gamma = 400 l^2 mu
g = (0.077, 5.5, 1.0)  # stiffness scaling g^u, g^v, g^theta
F = 1e4  # axial then transverse end force at particle 1 [N]
runs_q = {"fig9_factored": (0.65, 0.5, 0.5), "fig10_q0": (0.0, 0.0, 0.0)}
A, I = np.pi * R**2, np.pi * R**4 / 4
material = MicropolarMaterial.from_engineering(E, nu, length=ell, kappa_over_mu=0.1,
                                               gamma_over_l2mu=400.0)
law = GluedLaw(E, nu, R, B_factor)


def make_rod() -> Rod1D:
    return Rod1D(material, L, A, I, n_elements, MPI.COMM_SELF, scaling=g)


def two_steps(solve, X0, n):
    """Axial load at dof 0, then the transverse load at dof 1 with the axial held."""
    f = np.zeros(n)
    f[0] = F
    X, rep1 = solve(f, X0)
    f[1] = F
    X, rep2 = solve(f, X)
    return X, rep1.history + rep2.history


# ---- Fig. 8: DE string and scaled rod, uncoupled ----------------------------------------
string = GluedString(n_spheres, law)
q_de, hist = two_steps(lambda f, q: string.solve(f, string.clamp_dofs(), q),
                       string.axial_predictor(F), string.n_dofs)
rod_sol = make_rod().solve((F, F, 0.0), clamp="right")
Qde = q_de.reshape(-1, 3)
results = {"fig8_uncoupled": {
    "particles": {"x": string.x.tolist(), "u": Qde[:, 0].tolist(), "v": Qde[:, 1].tolist(),
                  "theta": Qde[:, 2].tolist()},
    "nodes": {k: {"x": getattr(rod_sol, f"x_{k}").tolist(), "value": getattr(rod_sol, k).tolist()}
              for k in ("u", "v", "theta")},
    "newton_history": hist}}

# ---- Fig. 8 against the seed: closed forms for both tips -----------------------------------
# The seed's text says the scaled rod and the string "can be nearly matched" (Fig. 8); ours
# differ 19x in the transverse tip. Both tips follow in closed form from the printed
# parameters, which locates the mismatch: the DE tip needs only eq. 60-61 (at the free tip
# sphere the moment balance forces every contact moment to zero, so our reading of eq. 66
# enters only through 1 + 1/B), the FE tip only eq. 39-40 with the row scalings.
n_c = n_spheres - 1
dn = (F / law.k_hertz) ** (2 / 3)  # eq. 60 per contact
k_t = law.k_mindlin * np.sqrt(R / 2 * dn)  # eq. 61: f_y = k_t delta_t
de_tip = (n_c * dn, n_c * F / k_t * (1 + 1 / B_factor))
m = material
GA, C = (m.mu + m.kappa) * A, m.lam + 2 * m.mu + m.kappa
bending = m.kappa / (m.mu + m.kappa) * F * L**3 / (3 * (C * I + m.gamma * A))  # seed form, g = 1
fe_tip = (F * L / (g[0] * C * A), (F * L / GA + bending) / g[1])  # g^theta = 1
seed_fig8 = {
    "seed_text": "DE and scaled FE 'can be nearly matched by scaling ... with the g's'; "
                 "rotations do not match closely (Fig. 8, image not in the OCR)",
    "de_tip_closed_form": {"u": de_tip[0], "v": de_tip[1]},
    "de_tip_computed": {"u": float(Qde[0, 0]), "v": float(Qde[0, 1])},
    "fe_tip_closed_form": {"u": fe_tip[0], "v": fe_tip[1]},
    "fe_tip_computed": {"u": float(rod_sol.u[0]), "v": float(rod_sol.v[0])},
    "transverse_ratio_de_over_fe": float(Qde[0, 1] / rod_sol.v[0]),
    "g_v_that_would_match": float(g[1] * rod_sol.v[0] / Qde[0, 1]),
    "mindlin_stiffness_factor_that_would_match": float(Qde[0, 1] / rod_sol.v[0]),
    "why": "The DE transverse tip is n_c F (1 + 1/B) / k_t with the standard Mindlin "
           "stiffness k_t = 4 mu a / (2 - nu), a = sqrt(R/2 delta_n), delta_n = (F/k_hertz)^(2/3) "
           "(contact shear; the contact moments vanish, the rotations ratchet 0, -delta_t/(B R), "
           "...); it is set by eq. 60-61 as printed and does not depend on our R^2 reading of "
           "eq. 66 beyond 1/B = 2 %. The FE tip with gamma = 400 l^2 mu is shear-dominated, "
           "F L / (g^v (mu + kappa) A). Matching needs g^v ~ 0.29 instead of the printed 5.5, "
           "or a 19x stiffer contact shear than eq. 61; with Fig. 4's gamma = 0.05 l^2 mu the "
           "scaled rod is 2.8x softer instead. No reading of g^v (row scaling, or scaling the "
           "shear energy in both rows: tip 0.50 mm) closes the gap. Not reproduced; the "
           "mismatch lies in the seed's printed parameters or figure, not in a path we can "
           "check (closed forms equal the solves).",
}

# ---- Fig. 9 and 10: coupled by eq. 122 ----------------------------------------------------
for name, q in runs_q.items():
    c = full_overlap(string, make_rod(), q)
    X, hist = two_steps(c.solve, string.axial_predictor(F), c.n)
    de_x, fe_x = c.force_split(X, 0)
    de_y, fe_y = c.force_split(X, 1)
    results[name] = c.fields(X) | {
        "q": q, "newton_history": hist,
        "end_force_split": {"axial_particle_1_DE": de_x, "axial_projected_FE": fe_x,
                            "transverse_particle_1_DE": de_y, "transverse_projected_FE": fe_y}}

# ---- output ------------------------------------------------------------------------------
if comm.rank == 0:
    args.out.mkdir(parents=True, exist_ok=True)
    results["seed_fig8_comparison"] = seed_fig8
    results["inputs"] = {"n_spheres": n_spheres, "R": R, "n_elements": n_elements, "L": L,
                         "E": E, "nu": nu, "B": B_factor, "l": ell, "kappa_over_mu": 0.1,
                         "gamma_over_l2mu": 400.0, "g": g, "F": F}
    (args.out / "results.json").write_text(json.dumps(results, indent=2))

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = ["fig8_uncoupled", *runs_q]
    fig, ax = plt.subplots(len(keys), 3, figsize=(13, 3.2 * len(keys)))
    for i, key in enumerate(keys):
        r = results[key]
        for j, (f, unit, s) in enumerate((("u", "cm", 100), ("v", "cm", 100), ("theta", "rad", 1))):
            ax[i, j].plot(100 * np.array(r["particles"]["x"]), s * np.array(r["particles"][f]),
                          "o", ms=4, label="particle centroids")
            ax[i, j].plot(100 * np.array(r["nodes"][f]["x"]), s * np.array(r["nodes"][f]["value"]),
                          "s-", ms=4, label="finite element nodes")
            ax[i, j].set(xlabel="x (cm)", ylabel=f"{f} ({unit})", title=f"{key}: {f}")
        ax[i, 0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "full_overlap.png", dpi=110)
    split = results["fig9_factored"]["end_force_split"]
    print(f"Fig. 9 axial split: particle 1 {split['axial_particle_1_DE']:.0f} N + projected node "
          f"{split['axial_projected_FE']:.0f} N (seed ~6300 + ~3600); tip u DE "
          f"{Qde[0, 0]:.4e} m, rod {rod_sol.u[0]:.4e} m; tip v DE {Qde[0, 1]:.4e} m, "
          f"rod {rod_sol.v[0]:.4e} m ({seed_fig8['transverse_ratio_de_over_fe']:.1f}x; g^v "
          f"{seed_fig8['g_v_that_would_match']:.3f} would match)")

# ---- checks --------------------------------------------------------------------------------
split = results["fig9_factored"]["end_force_split"]
assert abs(split["axial_particle_1_DE"] + split["axial_projected_FE"] - F) < 1e-8 * F
assert abs(split["transverse_particle_1_DE"] + split["transverse_projected_FE"] - F) < 1e-8 * F
assert np.allclose(results["fig10_q0"]["particles"]["u"], Qde[:, 0], rtol=1e-9)
assert abs(rod_sol.u[0] / Qde[0, 0] - 1) < 0.05, "g^u should match the DE axial tip"
assert np.allclose(de_tip, Qde[0, :2], rtol=1e-6), "DE tip = closed form (eq. 60-61)"
assert np.allclose(fe_tip, (rod_sol.u[0], rod_sol.v[0]), rtol=0.02), "FE tip = closed form"
