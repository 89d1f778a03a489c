"""Glued Hertz-Mindlin sphere string (seed 001 §2.3): tangent, Newton, closed forms."""

import numpy as np
import pytest

from dem.glued import GluedLaw, GluedString, NewtonDidNotConverge, newton

LAW = GluedLaw(E=29e9, nu=0.25, radius=0.005, B=50.0)
F = 1e4


def _string(n=21):
    return GluedString(n, LAW)


@pytest.mark.parametrize("compression", [1e-5, -1e-5])  # compressed and (glued) stretched
def test_tangent_matches_finite_differences(compression):
    s = _string(6)
    rng = np.random.default_rng(1)
    q = s.axial_predictor(F) * np.sign(compression) + 1e-4 * rng.standard_normal(s.n_dofs)
    q[0::3] = compression * np.arange(s.n)[::-1] + 1e-6 * rng.standard_normal(s.n)
    h = 1e-9
    Kfd = np.column_stack([(s.f_int(q + h * e) - s.f_int(q - h * e)) / (2 * h)
                           for e in np.eye(s.n_dofs)])
    K = s.tangent(q)
    assert np.abs(K - Kfd).max() < 1e-6 * np.abs(K).max()


def test_axial_string_matches_hertz_closed_form():
    s = _string()
    f = np.zeros(s.n_dofs)
    f[0] = F
    q, _ = s.solve(f, s.clamp_dofs(), s.axial_predictor(0.2 * F))
    dn = (F / LAW.k_hertz) ** (2 / 3)  # every contact carries F
    assert q[0] == pytest.approx(20 * dn, rel=1e-10)
    assert q[0] == pytest.approx(0.0091, rel=2e-2)  # seed: "after 1-cm of compression"


def test_transverse_closed_form_and_oscillating_rotations():
    # each contact carries f_y = P and moment balance gives theta_a + theta_b = -P/(B k a R):
    # rotations alternate (the seed's "ratcheting"), v is linear in x
    s = _string()
    f = np.zeros(s.n_dofs)
    f[0], f[1] = F, F
    q, _ = s.solve(f, s.clamp_dofs(), s.axial_predictor(F))
    Q = q.reshape(-1, 3)
    a = np.sqrt(LAW.radius / 2 * (F / LAW.k_hertz) ** (2 / 3))
    kt = LAW.k_mindlin * a
    assert Q[0, 1] == pytest.approx(20 * F * (1 + 1 / LAW.B) / kt, rel=1e-10)
    th_sum = -F / (LAW.B * kt * LAW.radius)
    assert np.allclose(Q[:-1, 2] + Q[1:, 2], th_sum, rtol=1e-10)
    assert np.allclose(Q[-2::-2, 2], th_sum) and np.allclose(Q[-1::-2, 2], 0, atol=1e-12)


def test_newton_converges_quadratically():
    s = _string()
    f = np.zeros(s.n_dofs)
    f[0], f[1] = F, 0.5 * F
    q, rep = s.solve(f, s.clamp_dofs(), s.axial_predictor(0.3 * F), rtol=1e-13)
    r = np.array(rep.history)
    assert rep.iterations >= 4 and r[-1] < 1e-13
    ratios = r[1:] / r[:-1] ** 2
    tail = ratios[(r[:-1] < 1e-2) & (r[1:] > 1e-14)]  # asymptotic range, above round-off
    assert tail.size >= 1 and tail.max() < 10.0
    assert np.allclose(s.f_int(q)[:-3], f[:-3], atol=1e-9 * F)


def test_failure_names_iteration_and_residual():
    s = _string(4)
    f = np.zeros(s.n_dofs)
    f[0] = F
    with pytest.raises(NewtonDidNotConverge, match="iteration 1.*singular") as e:
        s.solve(f, s.clamp_dofs(), np.zeros(s.n_dofs))  # zero Hertz stiffness at contact
    assert e.value.iteration == 1 and e.value.residual == pytest.approx(1.0)
    with pytest.raises(NewtonDidNotConverge, match="max_it = 2"):
        newton(lambda x: (np.array([x[0] ** 3 - 1.0]), np.array([[3 * x[0] ** 2]])),
               np.array([5.0]), np.array([], dtype=int), max_it=2)


@pytest.mark.parametrize("kw", [dict(E=-1.0), dict(nu=0.5), dict(radius=0.0), dict(B=-1.0)])
def test_bad_law_names_field(kw):
    args = dict(E=29e9, nu=0.25, radius=0.005, B=50.0) | kw
    with pytest.raises(ValueError, match=next(iter(kw))):
        GluedLaw(**args)
