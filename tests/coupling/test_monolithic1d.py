"""Monolithic DE x FE 1D coupling (seed 001 §2.4.3-2.4.4, eq. 122, 125-126)."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest

from coupling.monolithic1d import full_overlap, partial_overlap, rod_basis
from dem.glued import GluedLaw, GluedString
from granfe.materials import MicropolarMaterial
from granfe.rod1d import Rod1D

R, F = 0.005, 1e4
A, I = np.pi * R**2, np.pi * R**4 / 4
MAT = MicropolarMaterial.from_engineering(29e9, 0.25, length=0.01, kappa_over_mu=0.1,
                                          gamma_over_l2mu=400.0)
LAW = GluedLaw(29e9, 0.25, R, 50.0)
G_FULL = (0.077, 5.5, 1.0)


def _two_steps(c, X0):
    """Axial load at particle 1, then transverse with the axial held (seed §2.4.3)."""
    f = np.zeros(c.n)
    f[0] = F
    X, _ = c.solve(f, X0)
    f[1] = F
    return c.solve(f, X)[0]


def _full(q):
    s = GluedString(21, LAW)
    c = full_overlap(s, Rod1D(MAT, 0.2, A, I, 5, MPI.COMM_SELF, scaling=G_FULL), q)
    return c, _two_steps(c, s.axial_predictor(F))


def test_fig9_force_split_sums_to_load_and_matches_seed():
    c, X = _full((0.65, 0.5, 0.5))
    de, fe = c.force_split(X, 0)
    assert de + fe == pytest.approx(F, rel=1e-9)
    assert de == pytest.approx(6.3e3, rel=0.03) and fe == pytest.approx(3.6e3, rel=0.03)
    de_v, fe_v = c.force_split(X, 1)
    assert de_v + fe_v == pytest.approx(F, rel=1e-9)


def test_q0_equals_pure_string():
    c, X = _full((0.0, 0.0, 0.0))
    s = c.string
    f = np.zeros(s.n_dofs)
    f[0], f[1] = F, F
    q, _ = s.solve(f, s.clamp_dofs(), s.axial_predictor(F))
    assert np.abs(X - q).max() < 1e-10 * np.abs(q).max()


def test_projection_is_exact_for_fe_motions_and_q1_is_refused():
    s = GluedString(21, LAW)
    rod = Rod1D(MAT, 0.2, A, I, 5, MPI.COMM_SELF)
    c = full_overlap(s, rod, (0.5, 0.5, 0.5))
    D = np.random.default_rng(0).standard_normal(c.T.shape[0])
    D[rod.end_dofs("right")] = 0.0
    assert np.abs(c.T @ (rod_basis(rod, s.x) @ D) - D).max() < 1e-12 * np.abs(D).max()
    with pytest.raises(ValueError, match="q must"):
        full_overlap(s, rod, (1.0, 0.5, 0.5))


@pytest.mark.parametrize("g,q", [((1, 1, 1), (0, 0, 0)), ((0.0195, 0.8, 0.85), (0, 0, 0.9))])
def test_partial_overlap_transmits_the_load_to_the_clamp(g, q):
    s = GluedString(11, LAW)
    rod = Rod1D(MAT, 0.16, A, I, 4, MPI.COMM_SELF, scaling=g, x0=0.04)
    c = partial_overlap(s, rod, 0.583, q)
    X0 = np.zeros(c.n)
    X0[:s.n_dofs] = s.axial_predictor(F)
    X = _two_steps(c, X0)
    # global balance through the coupling: the (scaled) rod reaction equals the applied load
    rod.set_cell_weights("u", 1.0), rod.set_cell_weights("v", 1.0)
    reaction = (rod.K @ (c.T @ X))[rod.end_dofs("right")]
    assert reaction[0] == pytest.approx(-F, rel=1e-8)
    assert reaction[1] == pytest.approx(-F, rel=1e-8)
    # the string's pure-DE part carries the whole load in every contact
    fc = s.contact_forces(c.S @ X)
    assert np.allclose(fc[:3, :2], F, rtol=1e-9)
