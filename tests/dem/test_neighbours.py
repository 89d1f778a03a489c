"""Linked-cell Verlet lists against brute force; history carried across rebuilds."""

import numpy as np
import pytest

import dem
from dem.neighbours import brute_force_pairs, build_pairs, carry_history


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cell_list_equals_brute_force(dim, seed):
    rng = np.random.default_rng(seed)
    n = 400
    x = rng.uniform(0, 0.03 if dim == 3 else 0.06, (n, 3))
    if dim == 2:
        x[:, 2] = 0.0
    r = rng.uniform(0.5e-3, 1.5e-3, n)  # polydisperse
    for skin in (0.0, 2e-4):
        pi, pj = build_pairs(x, r, skin)
        bi, bj = brute_force_pairs(x, r, skin)
        assert len(pi) > 50
        assert np.array_equal(pi * n + pj, np.sort(bi * n + bj))
        assert (pi < pj).all()


@pytest.mark.parametrize("n", [400, 5000])
def test_skipped_rows_make_no_pairs_among_themselves(n):
    """``build_pairs(skip=)`` is the full list less the pairs of two skipped rows, in the
    same order (the serial kernel and the parallel one above PAIRS_PARALLEL_MIN rows); all
    rows skipped: no pairs."""
    rng = np.random.default_rng(7)
    x = rng.uniform(0, 0.01 * (n / 400) ** (1 / 3), (n, 3))
    r = rng.uniform(0.5e-3, 1.5e-3, n)
    skip = rng.random(n) < 0.3
    skip[:5] = True   # (a dense clump of skipped rows among the others)
    x[:5] = x[5] + rng.uniform(-1e-4, 1e-4, (5, 3))
    pi, pj = build_pairs(x, r, 2e-4)
    keep = ~(skip[pi] & skip[pj])
    qi, qj = build_pairs(x, r, 2e-4, skip)
    assert keep.sum() < len(pi) and np.array_equal(qi, pi[keep]) and np.array_equal(qj, pj[keep])
    assert len(build_pairs(x, r, 2e-4, np.ones(n, bool))[0]) == 0
    assert np.array_equal(build_pairs(x, r, 2e-4, np.zeros(n, bool))[0], pi)


def test_history_carried_by_key():
    old = np.array([3, 7, 12, 20])
    hist = np.arange(12.0).reshape(4, 3)
    slip = np.array([0, 1, 0, 1], np.int8)
    new = np.array([1, 7, 20, 25])
    h, s = carry_history(old, new, hist, slip)
    assert np.array_equal(h, [[0, 0, 0], [3, 4, 5], [9, 10, 11], [0, 0, 0]])
    assert np.array_equal(s, [0, 1, 1, 0])


def test_rebuild_keeps_tangential_springs():
    """A sliding-free sticking contact keeps its spring across forced rebuilds."""
    mat = dem.ContactMaterial(E=1e7, nu=0.3, density=1000.0, friction=0.9, restitution=0.5)
    x = [[0, 0, 0], [1.999e-3, 0, 0], [5e-3, 5e-3, 5e-3]]
    p = dem.Particles.spheres(x, 1e-3, 1000.0, v=[[0, 1e-3, 0], [0, 0, 0], [0, 0, 0]],
                              kind=[dem.FREE, dem.FIXED, dem.FREE])
    sim = dem.Simulation(p, mat, allow_overlap=True, skin=1e-5)
    sim.step(20)
    k = np.flatnonzero((sim.nl.pi == 0) & (sim.nl.pj == 1))[0]
    s_before = sim.nl.hist[k].copy()
    assert np.linalg.norm(s_before) > 0
    sim.nl.build(p.x, p.radius, sim.walls.point, sim.walls.normal)
    k = np.flatnonzero((sim.nl.pi == 0) & (sim.nl.pj == 1))[0]
    assert np.array_equal(sim.nl.hist[k], s_before)
