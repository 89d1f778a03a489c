"""Calibration of the continuum from periodic DEM cells: the moduli of regular lattices equal
their closed forms, a random packing of frictional disks has the friction angle of the
literature, and the calibrated continuum follows the cell to its peak."""

import math

import numpy as np
import pytest

import dem
from coupling.calibration import CellTest, calibrate, continuum_shear
from dem.bonded import hexagonal_lattice_micropolar

KN, KT = 2e5, 1e5            # N/m per m thickness, the 2D scenes' law


def disks(friction=0.5):
    return dem.ContactMaterial(E=KN, nu=0.25, density=2650.0, friction=friction, restitution=0.5,
                               law="linear", kn=KN, kt=KT)


def test_hexagonal_lattice_moduli_are_the_closed_form():
    """A hexagonal lattice of sticking disks deforms affinely: K = lam + G = sqrt(3)/2 kn,
    G = sqrt(3)/4 (kn + kt), kappa = sqrt(3) kt (spins held: the tangential springs carry the
    relative rotation), M = lam + 2 G; to 3e-3, the geometric stiffness of the prestress
    (contact overlap p / sqrt(3) kn = 6e-4 of the spacing at p = 200 Pa). Today's estimate
    (Z / 6 = 1) is the closed form itself."""
    cal = calibrate(CellTest(disks(), 1.5e-3, packing="lattice", spread=0.0, grains=36,
                             pressure=200.0, shear_strain=0.0))
    closed = hexagonal_lattice_micropolar(KN, KT, 0.0)
    G = closed["mu"] + closed["kappa"] / 2
    assert cal.coordination == 6.0
    assert cal.bulk_modulus == pytest.approx(closed["lam"] + G, rel=3e-3)
    assert cal.shear_modulus == pytest.approx(G, rel=3e-3)
    assert cal.kappa == pytest.approx(closed["kappa"], rel=3e-3)
    assert cal.oedometric_modulus == pytest.approx(cal.lam + 2 * cal.shear_modulus, rel=1e-6)
    for k in ("lam", "mu", "kappa"):
        assert cal.estimate[k] == pytest.approx(closed[k], rel=1e-12)


def test_fcc_bulk_and_coupling_moduli_are_the_voigt_ones():
    """An fcc lattice of Hertz-Mindlin spheres: every grain is a centre of symmetry and the
    contact directions' second moment is isotropic, so the affine (Voigt) bulk modulus
    phi Z kn / (6 pi R) and coupling modulus A kt / 3 at the contacts' tangent stiffnesses
    are exact (to 1e-2: the prestress)."""
    spheres = dem.ContactMaterial(E=2.9e7, nu=0.25, density=2650.0, friction=0.5, restitution=0.5)
    cal = calibrate(CellTest(spheres, 2e-3, dim=3, packing="lattice", spread=0.0, grains=32,
                             pressure=2e3, shear_strain=0.0))
    voigt = cal.estimate
    assert cal.coordination == 12.0
    assert cal.bulk_modulus == pytest.approx(voigt["lam"] + 2 * (voigt["mu"] + voigt["kappa"] / 2) / 3,
                                             rel=1e-2)
    assert cal.kappa == pytest.approx(voigt["kappa"], rel=1e-2)


@pytest.fixture(scope="module")
def random_disks():
    return calibrate(CellTest(disks(), 1.5e-3, grains=200, pressure=2e3, seed=0))


def test_random_disks_friction_angle_is_the_literature_one(random_disks):
    """200 polydisperse disks (contact friction 0.5) sheared at constant normal stress: the
    critical-state friction angle is that of 2D disk packings, sin phi = 0.26-0.30 (da Cruz
    et al. 2005, GDR MiDi 2004: 15-17.5 deg), within +-5 deg for a cell this small; the
    packing made dense (compressed without friction) peaks above it and dilates."""
    cal = random_disks
    assert 12.0 < cal.friction_critical_deg < 22.0
    assert cal.friction_peak_deg > cal.friction_critical_deg + 3.0
    assert cal.dilatancy_deg > 2.0
    shear = cal.curves["shear_to_failure"]
    normal = np.array(shear["normal_stress"][10:])                       # the servo held p
    assert abs(normal.mean() / 2e3 - 1) < 0.03 and np.allclose(normal, 2e3, rtol=0.25)


def test_random_disks_are_softer_than_the_lattice_estimate(random_disks):
    """Elastic moduli of the disordered packing: positive, below today's affine lattice
    estimate (non-affine relaxation), and consistent (M = lam + 2 G within 10 %)."""
    cal = random_disks
    est = cal.estimate
    assert 0 < cal.shear_modulus < est["mu"] + est["kappa"] / 2
    assert 0 < cal.bulk_modulus < est["lam"] + est["mu"] + est["kappa"] / 2
    assert 0 < cal.kappa
    assert cal.oedometric_modulus == pytest.approx(cal.lam + 2 * cal.shear_modulus, rel=0.1)


def test_calibrated_continuum_peaks_with_the_cell(random_disks):
    """The calibrated plane-strain Drucker-Prager continuum through the same test peaks at
    the cell's peak friction angle (issue figure: within 5 %)."""
    model = continuum_shear(random_disks, steps=100)
    peak = math.degrees(math.asin(max(model["sin_friction"])))
    assert peak == pytest.approx(random_disks.friction_peak_deg, rel=0.05)
    assert np.allclose(model["normal_stress"], 2e3, rtol=1e-8)


@pytest.mark.parametrize("kwargs, key", [
    (dict(radius=-1.0), "radius"),
    (dict(dim=4), "dim"),
    (dict(packing="hcp"), "packing"),
    (dict(increment=0.5), "increment"),
])
def test_cell_test_is_validated(kwargs, key):
    with pytest.raises(ValueError, match=key):
        CellTest(**{"material": disks(), "radius": 1e-3, **kwargs})
