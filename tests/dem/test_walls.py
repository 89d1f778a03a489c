"""Plane walls: the rigid wall's contact parameters, its stiffness under a resting grain and
its restitution at the default step (the wall rules of `dem.walls.PlaneWall`)."""

import math

import numpy as np
import pytest

import dem
from dem.contact import P_BETA, P_ESTAR, P_GSTAR, P_KN, P_KT, P_MUS, beta_of_restitution, pair_table

R, RHO, E, NU, G = 1.0e-3, 2650.0, 2.9e8, 0.25, 9.81


def hertz(e=0.5, E_=E, nu=NU, mu=0.5):
    return dem.ContactMaterial(E=E_, nu=nu, density=RHO, friction=mu, restitution=e)


def linear(e=0.5):
    return dem.ContactMaterial(E=E, nu=NU, density=RHO, friction=0.5, restitution=e,
                               law="linear", kn=2e4, kt=1.6e4)


def test_rigid_wall_parameters_are_the_particles_alone():
    """Entry [a, nmat + b]: E*, G* of material a alone, kn, kt twice a's; restitution and
    friction mixed with the wall's material b as for a compliant wall."""
    a, b = hertz(0.3, mu=0.5), hertz(0.7, E_=1e10, nu=0.3, mu=0.2)
    t = pair_table([a, b])
    assert t.shape[:2] == (2, 4)
    assert t[0, 2 + 1, P_ESTAR] == pytest.approx(E / (1 - NU**2), rel=1e-14)
    assert t[0, 2 + 1, P_GSTAR] == pytest.approx(E / (2 * (2 - NU) * (1 + NU)), rel=1e-14)
    assert t[0, 2 + 0, P_ESTAR] == pytest.approx(2 * t[0, 0, P_ESTAR], rel=1e-14)
    for col in (P_BETA, P_MUS):  # the surface: as the compliant wall of material b
        assert t[0, 2 + 1, col] == t[0, 1, col]
    assert t[0, 3, P_BETA] == pytest.approx(beta_of_restitution(0.5), rel=1e-14)
    lt = pair_table([linear()])
    assert (lt[0, 1, P_KN], lt[0, 1, P_KT]) == (4e4, 3.2e4)
    assert (lt[0, 0, P_KN], lt[0, 0, P_KT]) == pytest.approx((2e4, 1.6e4), rel=1e-14)


@pytest.mark.parametrize("rigid", [False, True])
def test_resting_grain_sinks_by_the_hertz_overlap(rigid):
    """A grain settled on the wall under gravity: 4/3 E* sqrt(R) delta^(3/2) = m g with
    E* = E/(1 - nu^2) (rigid) or half that (a wall of the grain's material)."""
    p = dem.Particles.spheres([[0.0, 0.0, R]], R, RHO)
    sim = dem.Simulation(p, hertz(0.1), [dem.PlaneWall((0, 0, 0), (0, 0, 1), rigid=rigid)],
                         (0, 0, -G))
    sim.step(4000)
    estar = E / (1 - NU**2) / (1 if rigid else 2)
    delta = (3 * float(p.mass[0]) * G / (4 * estar * math.sqrt(R))) ** (2 / 3)
    assert abs(p.v[0]).max() < 1e-9
    assert R - p.x[0, 2] == pytest.approx(delta, rel=1e-9)
    assert sim.walls.force[0, 2] == pytest.approx(-float(p.mass[0]) * G, rel=1e-9)


def bounce(mat, phase, rigid=True):
    """Restitution of a grain dropped at 1 m/s onto a rigid wall at the default step, the
    touch at ``phase`` (0..1) of a step."""
    p = dem.Particles.spheres([[0.0, 0.0, 4 * R]], R, RHO, v=[[0, 0, -1.0]])
    walls = [dem.PlaneWall((0, 0, 0), (0, 0, 1), rigid=rigid)]
    dt = dem.default_time_step(p, mat)
    p.x[0, 2] = R + dt * (2.0 + phase)
    sim = dem.Simulation(p, mat, walls)
    touched = False
    for _ in range(2000):
        sim.step(1)
        touched |= bool(p.x[0, 2] < R)
        if touched and p.x[0, 2] >= R and p.v[0, 2] > 0:
            return p.v[0, 2]
    raise AssertionError("no separation")


@pytest.mark.parametrize("e", [0.1, 0.5, 0.9])
@pytest.mark.parametrize("law", ["hertz_mindlin", "linear"])
def test_rigid_wall_restitution_at_the_default_step(law, e):
    """The dashpot scales with the stiffness, so the stiffer wall keeps the input e (the
    contact ODE's e, tests/dem/test_restitution.py): each of 4 touch phases within 1 %."""
    mat = hertz(e) if law == "hertz_mindlin" else linear(e)
    es = np.array([bounce(mat, (k + 0.5) / 4) for k in range(4)])
    assert np.abs(es / e - 1).max() < 0.01, es


def test_rigid_flag_is_checked_and_carried():
    with pytest.raises(ValueError, match="PlaneWall.rigid"):
        dem.PlaneWall((0, 0, 0), (0, 0, 1), rigid="yes")
    w = dem.walls.WallSet([dem.PlaneWall((0, 0, 0), (0, 0, 1), material=1, rigid=True),
                           dem.PlaneWall((0, 0, 1), (0, 0, -1), material=1)])
    assert w.table_columns(3).tolist() == [4, 1]
    assert "rigid" not in w.state_dict()  # set-up, like the number of walls


def test_free_only_wall_lets_ghosts_through_until_they_are_released():
    """A ``free_only`` plate (a loading plate the cone pierces): a GHOST sphere behind it
    feels no force and puts none on it; a FREE sphere pressing on it does; a GHOST released
    with ``kinds_changed`` touches it from the next pass on."""
    with pytest.raises(ValueError, match="PlaneWall.free_only"):
        dem.PlaneWall((0, 0, 0), (0, 0, -1), free_only=1)
    mat = dem.ContactMaterial(E=1e7, nu=0.25, density=2650.0, friction=0.5, restitution=0.5)
    r = 1e-3
    # the plate at z = 0 facing down; a ghost 3 r above it (behind), a free grain pressing it
    x = np.array([[0.0, 0.0, 3 * r], [0.01, 0.0, -0.9 * r]])
    p = dem.Particles.spheres(x, np.full(2, r), 2650.0, kind=np.array([dem.GHOST, 0], np.int8))
    plate = dem.PlaneWall((0, 0, 0), (0, 0, -1), free_only=True)
    sim = dem.Simulation(p, mat, walls=[plate], allow_overlap=True)
    sim.compute_forces(update_history=False)
    assert np.all(sim.p.force[0] == 0.0)
    assert sim.p.force[1, 2] < 0 and sim.walls.force[0, 2] == pytest.approx(-sim.p.force[1, 2])
    # the same with an ordinary wall: the ghost behind it is a deep overlap
    sim2 = dem.Simulation(dem.Particles.spheres(x, np.full(2, r), 2650.0, kind=np.array([dem.GHOST, 0], np.int8)),
                          mat, walls=[dem.PlaneWall((0, 0, 0), (0, 0, -1))], allow_overlap=True)
    sim2.compute_forces(update_history=False)
    assert sim2.p.force[0, 2] < 0
    # released: the former ghost meets the plate
    sim.p.x[0, 2] = -0.9 * r
    sim.p.kind[0] = 0
    sim.kinds_changed()
    sim.compute_forces(update_history=False)
    assert sim.p.force[0, 2] == pytest.approx(sim.p.force[1, 2], rel=1e-12)
