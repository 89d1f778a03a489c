"""Overlapping particles at the start: named by count and largest overlap, and removable."""

import numpy as np
import pytest

import dem
from dem.packing import remove_overlaps


def overlapping(dim, n=80, seed=3):
    rng = np.random.default_rng(seed)
    x = np.zeros((n, 3))
    x[:, :dim] = rng.random((n, dim)) * 0.02
    return dem.Particles.spheres(x[:, :dim] if dim == 2 else x, 1e-3, 2650.0, dim=dim)


@pytest.mark.parametrize("dim", [2, 3])
def test_overlaps_named_then_removed(dim):
    p = overlapping(dim)
    mat = dem.ContactMaterial(E=1e7, nu=0.25, density=2650.0, friction=0.5, restitution=0.5)
    with pytest.raises(dem.OverlapError, match=r"(\d+) overlapping particle pairs .* largest overlap "
                                                r".*remove_overlaps"):
        dem.Simulation(p, mat)
    p.kind[:5] = dem.GHOST
    held = p.x[:5].copy()
    its, worst = remove_overlaps(p, iterations=5000)
    assert worst <= 1e-13 and its > 0
    assert np.array_equal(p.x[:5], held)          # ghosts are not moved
    if dim == 2:
        assert np.all(p.x[:, 2] == 0.0)
    count, largest, _ = p.check_overlaps(allow=True, tol=1e-13)
    assert count == 0 and largest <= 1e-13
    dem.Simulation(p, mat)  # accepted now


def test_remove_overlaps_reports_failure():
    p = overlapping(3, n=50)
    with pytest.raises(dem.OverlapError, match="remove_overlaps: 1 iterations left an overlap"):
        remove_overlaps(p, iterations=1)
