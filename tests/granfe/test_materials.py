import math

import pytest

from granfe.materials import MicropolarMaterial, lame_from_engineering


def test_seed001_constants():
    # seed 001 §2.2.5: E = 10 GPa, nu = 0.3, kappa = 0.1 mu, gamma = 0.05 l^2 mu, l = 1 cm
    mat = MicropolarMaterial.from_engineering(
        10e9, 0.3, length=0.01, kappa_over_mu=0.1, gamma_over_l2mu=0.05
    )
    lam, mu = lame_from_engineering(10e9, 0.3)
    assert mat.lam == pytest.approx(lam, rel=1e-15)
    assert mat.mu == pytest.approx(10e9 / 2.6, rel=1e-15)
    assert mat.kappa == pytest.approx(0.1 * mu, rel=1e-15)
    assert mat.gamma == pytest.approx(0.05 * 1e-4 * mu, rel=1e-15)
    assert mat.E == pytest.approx(10e9, rel=1e-12)
    assert mat.nu == pytest.approx(0.3, rel=1e-12)


def test_coupling_number_round_trip():
    mat = MicropolarMaterial.from_engineering(1e6, 0.25, length=1.0, coupling_number=0.5)
    assert mat.coupling_number == pytest.approx(0.5, rel=1e-14)
    assert math.isfinite(mat.bending_length)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(lam=1.0, mu=-1.0, kappa=0.1), "mu"),
        (dict(lam=1.0, mu=1.0, kappa=-0.1), "kappa"),
        (dict(lam=-1.0, mu=1.0, kappa=0.1), "lam"),
        (dict(lam=1.0, mu=1.0, kappa=0.1, gamma=0.0), "gamma"),
        (dict(lam=1.0, mu=1.0, kappa=0.1, gamma=1.0, beta=2.0), "beta"),
        (dict(lam=1.0, mu=1.0, kappa=0.1, gamma=1.0, alpha=-5.0), "alpha"),
        (dict(lam=1.0, mu=1.0, kappa=0.1, rho=0.0), "rho"),
        (dict(lam=1.0, mu=1.0, kappa=0.1, j=float("nan")), "j"),
    ],
)
def test_rejects_non_physical(kwargs, field):
    with pytest.raises(ValueError, match=rf"MicropolarMaterial\.{field}"):
        MicropolarMaterial(**kwargs)


@pytest.mark.parametrize("E, nu, field", [(-1.0, 0.3, "E"), (1.0, 0.5, "nu"), (1.0, -1.2, "nu")])
def test_engineering_rejects(E, nu, field):
    with pytest.raises(ValueError, match=field):
        lame_from_engineering(E, nu)
