"""Particles: construction, validation with named errors, overlap report."""

import math

import numpy as np
import pytest

import dem


def test_sphere_and_disk_mass_inertia():
    p3 = dem.Particles.spheres([[0, 0, 0]], 2e-3, 2500.0)
    m = 4 / 3 * math.pi * 8e-9 * 2500
    assert p3.mass[0] == pytest.approx(m, rel=1e-14)
    assert p3.inertia[0] == pytest.approx(0.4 * m * 4e-6, rel=1e-14)
    p2 = dem.Particles.spheres([[0, 0]], 2e-3, 2500.0, dim=2)
    assert p2.x.shape == (1, 3) and p2.dim == 2
    assert p2.mass[0] == pytest.approx(math.pi * 4e-6 * 2500, rel=1e-14)
    assert p2.inertia[0] == pytest.approx(0.5 * p2.mass[0] * 4e-6, rel=1e-14)
    assert p3.kind.dtype == np.int8 and p3.material.dtype == np.int32
    assert p3.force.shape == p3.torque.shape == (1, 3)


@pytest.mark.parametrize("kwargs, match", [
    (dict(radius=[1e-3, -1e-3]), r"radius.*particle 1"),
    (dict(radius=[1e-3, 0.0]), r"radius.*particle 1"),
    (dict(x=[[0, 0, 0], [np.nan, 0, 0]]), r"x must be finite; particle 1"),
    (dict(x=[[0, 0, 0, 0], [1, 0, 0, 0]]), r"x must have shape"),
    (dict(density=-1.0), r"density.*particle 0"),
    (dict(v=np.zeros((3, 3))), r"v must have shape \(2, 3\)"),
])
def test_bad_input_names_field_and_index(kwargs, match):
    args = dict(x=[[0, 0, 0], [1, 0, 0]], radius=1e-3, density=1000.0) | kwargs
    with pytest.raises(ValueError, match=match):
        dem.Particles.spheres(**args)


def test_2d_rejects_out_of_plane_motion():
    with pytest.raises(ValueError, match=r"omega\[:, \[0, 1\]\].*particle 0"):
        dem.Particles.spheres([[0, 0]], 1e-3, 1000.0, dim=2, omega=[[1.0, 0, 0]])


def test_check_overlaps_reports_count_and_largest():
    x = [[0, 0, 0], [1.9e-3, 0, 0], [10e-3, 0, 0], [11.95e-3, 0, 0]]
    p = dem.Particles.spheres(x, 1e-3, 1000.0)
    with pytest.raises(dem.OverlapError, match=r"2 overlapping.*0.0001 m.*\(0, 1\)"):
        p.check_overlaps()
    count, worst, pair = p.check_overlaps(allow=True)
    assert (count, pair) == (2, (0, 1)) and worst == pytest.approx(1e-4, rel=1e-9)
    with pytest.raises(dem.OverlapError):
        dem.Simulation(p, dem.ContactMaterial(E=1e7, nu=0.3, density=1000.0, friction=0.5,
                                              restitution=0.5))


def test_material_validation():
    ok = dict(E=1e7, nu=0.3, density=1000.0, friction=0.5, restitution=0.5)
    for field, bad in [("E", -1.0), ("nu", 0.5), ("restitution", 0.0), ("friction", -0.1),
                       ("law", "hooke"), ("density", 0.0), ("rolling_friction", -1.0)]:
        with pytest.raises(dem.MaterialError, match=f"ContactMaterial.{field}"):
            dem.ContactMaterial(**(ok | {field: bad}))
    with pytest.raises(dem.MaterialError, match="kn"):
        dem.ContactMaterial(**ok, law="linear")
    with pytest.raises(dem.MaterialError, match="friction_dynamic"):
        dem.ContactMaterial(**ok, friction_dynamic=0.6)


def test_state_dict_roundtrip(tmp_path):
    p = dem.Particles.spheres(np.random.default_rng(0).random((5, 3)), 1e-3, 1000.0)
    np.savez(tmp_path / "s.npz", **p.state_dict())
    q = dem.Particles.from_state_dict(np.load(tmp_path / "s.npz"))
    assert np.array_equal(p.x, q.x) and np.array_equal(p.inertia, q.inertia)
