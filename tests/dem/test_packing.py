"""Packings: no overlap (checked by an independent cKDTree route), inside the box, fraction."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from dem.packing import PackingError, lattice_packing, random_packing, solid_fraction


def _min_gap(x, r):
    pairs = cKDTree(x).query_pairs(2 * r.max(), output_type="ndarray")
    if len(pairs) == 0:
        return np.inf
    d = np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1)
    return (d - r[pairs].sum(axis=1)).min()


def _inside(x, r, lo, hi):
    dim = len(lo)
    return np.all(x[:, :dim] - r[:, None] >= np.asarray(lo) - 1e-12) and np.all(
        x[:, :dim] + r[:, None] <= np.asarray(hi) + 1e-12)


@pytest.mark.parametrize("lo,hi,kind,phi_bulk", [
    ((0, 0), (1.0, 0.8), "hex", np.pi / (2 * np.sqrt(3))),
    ((0, 0), (1.0, 0.8), "sc", np.pi / 4),
    ((0, 0, 0), (1.0, 0.8, 0.6), "fcc", np.pi / (3 * np.sqrt(2))),
    ((0, 0, 0), (1.0, 0.8, 0.6), "sc", np.pi / 6)])
def test_lattice(lo, hi, kind, phi_bulk):
    r = 0.02
    x, rad = lattice_packing(lo, hi, r, kind)
    assert _min_gap(x, rad) > -1e-12 and _inside(x, rad, lo, hi)
    if len(lo) == 2:
        assert np.all(x[:, 2] == 0)
    # touching lattice: nearest-neighbour distance is exactly 2r
    d, _ = cKDTree(x).query(x, k=2)
    np.testing.assert_allclose(d[:, 1], 2 * r, rtol=1e-12)
    # bulk fraction approached up to a boundary layer of about one spacing
    phi = solid_fraction(rad, lo, hi)
    assert 0.75 * phi_bulk < phi <= phi_bulk + 1e-12


def test_lattice_jitter_keeps_gaps_and_is_reproducible():
    lo, hi = (0, 0, 0), (0.3, 0.3, 0.3)
    shift = 0.01 * 0.05  # the jittered lattice keeps one jitter radius more from the walls
    x0, r = lattice_packing((shift,) * 3, (0.3 - shift,) * 3, 0.01, "fcc", gap=0.05)
    x1, _ = lattice_packing(lo, hi, 0.01, "fcc", gap=0.05, jitter=1.0, seed=3)
    x2, _ = lattice_packing(lo, hi, 0.01, "fcc", gap=0.05, jitter=1.0, seed=3)
    np.testing.assert_array_equal(x1, x2)
    move = np.linalg.norm(x1 - x0, axis=1)
    assert move.max() <= 0.01 * 0.05 + 1e-15 and move.max() > 0.5 * 0.01 * 0.05
    assert _min_gap(x1, r) >= -1e-15 and _inside(x1, r, lo, hi)


@pytest.mark.parametrize("lo,hi,dist,target", [
    ((0, 0), (0.2, 0.1), "uniform", 0.45),
    ((0, 0, 0), (0.05, 0.04, 0.04), "lognormal", 0.33),
    ((0, 0, 0), (0.05, 0.04, 0.04), "uniform", 0.30)])
def test_random_packing(lo, hi, dist, target):
    x, r = random_packing(lo, hi, 0.001, 0.0025, target, dist, seed=7)
    assert _min_gap(x, r) >= 0 and _inside(x, r, lo, hi)
    assert r.min() >= 0.001 and r.max() <= 0.0025 and np.ptp(r) > 0
    phi = solid_fraction(r, lo, hi)
    assert 0.99 * target <= phi < target + 1e-2
    x2, r2 = random_packing(lo, hi, 0.001, 0.0025, target, dist, seed=7)
    np.testing.assert_array_equal(x, x2)
    np.testing.assert_array_equal(r, r2)
    x3, _ = random_packing(lo, hi, 0.001, 0.0025, target, dist, seed=8)
    assert x3.shape != x.shape or not np.array_equal(x3, x)


def test_random_packing_gives_up_with_the_achieved_fraction():
    lo, hi = (0, 0), (0.1, 0.1)
    with pytest.raises(PackingError, match=r"solid fraction 0\.\d+ reached of target 0\.8") as e:
        random_packing(lo, hi, 0.002, 0.002, 0.8, max_tries=200)
    assert e.value.fraction == pytest.approx(solid_fraction(e.value.radius, lo, hi))
    assert _min_gap(e.value.x, e.value.radius) >= 0
    with pytest.warns(RuntimeWarning, match="gave up"):
        random_packing(lo, hi, 0.002, 0.002, 0.8, max_tries=200, strict=False)


@pytest.mark.parametrize("call,match", [
    (lambda: lattice_packing((0, 0), (1, 1), -0.1), "radius"),
    (lambda: lattice_packing((0, 0), (0.1, 1), 0.1), "too small"),
    (lambda: lattice_packing((0, 0), (1, 1), 0.1, "fcc"), "lattice kind"),
    (lambda: lattice_packing((0, 0), (1, 1), 0.1, jitter=2), "jitter"),
    (lambda: lattice_packing((0, 0), (1, 1), 0.1, gap=-1), "gap"),
    (lambda: lattice_packing((0, 1), (1, 0), 0.1), "hi > lo"),
    (lambda: random_packing((0, 0), (1, 1), 0.2, 0.1, 0.3), "r_min"),
    (lambda: random_packing((0, 0), (1, 1), -0.2, 0.1, 0.3), "r_min"),
    (lambda: random_packing((0, 0), (0.1, 1), 0.1, 0.2, 0.3), "too small"),
    (lambda: random_packing((0, 0), (1, 1), 0.01, 0.02, 1.3), "target_fraction"),
    (lambda: random_packing((0, 0), (1, 1), 0.01, 0.02, 0.3, "gauss"), "distribution")])
def test_bad_input(call, match):
    with pytest.raises(ValueError, match=match):
        call()
