"""Rolling resistance: a constant torque mu_r |F_n| R* against the relative spin."""

import numpy as np
import pytest

from dem import ContactMaterial, Particles, PlaneWall, Simulation

R, G, V0 = 1e-3, 9.81, 0.05


def rolling_ball(dim, mu_r):
    """A ball settled on a floor, then set rolling along +x without slip: a fresh Simulation
    (the blow-up guard counts the energy put in during a run, not between runs)."""
    mat = ContactMaterial(E=1e8, nu=0.25, density=2650.0, friction=0.5, restitution=0.2,
                          rolling_friction=mu_r)
    up = dim - 1
    normal = np.zeros(3)
    normal[up] = 1.0
    floor = [PlaneWall((0.0, 0.0, 0.0), tuple(normal))]
    x = np.zeros((1, dim))
    x[0, up] = R
    gravity = np.zeros(3)
    gravity[up] = -G
    sim = Simulation(Particles.spheres(x, R, 2650.0, dim=dim), mat, walls=floor,
                     gravity=tuple(gravity), allow_overlap=True)
    sim.step(3000)  # settle onto the floor (bounces die out with e = 0.2)
    p = sim.p
    p.v[:] = 0.0
    p.v[0, 0] = V0
    # the contact point (-R e_up) at rest: omega x (-R e_up) = -V0 e_x
    if dim == 3:
        p.omega[0] = (0.0, V0 / R, 0.0)
    else:
        p.omega[0] = (0.0, 0.0, -V0 / R)
    return Simulation(p, mat, walls=floor, gravity=tuple(gravity), allow_overlap=True)


def spin(sim, dim):
    return sim.p.omega[0, 1] if dim == 3 else -sim.p.omega[0, 2]


@pytest.mark.parametrize("dim", [3, 2])
def test_rolling_ball_decelerates_at_the_closed_form_rate(dim):
    """m a = -F, I a / R = F R - M with M = mu_r m g R: a = -mu_r g / (1 + I / (m R^2)),
    5/7 mu_r g for a sphere and 2/3 mu_r g for a disk."""
    mu_r = 0.05
    sim = rolling_ball(dim, mu_r)
    n = int(0.5 * V0 / (mu_r * G) / sim.dt)  # half way to rest
    sim.step(n)
    a = (sim.p.v[0, 0] - V0) / (n * sim.dt)
    shape = 2.0 / 5.0 if dim == 3 else 0.5
    assert a == pytest.approx(-mu_r * G / (1.0 + shape), rel=0.02)
    # still rolling, not sliding: the contact point's slip is small against v
    assert abs(sim.p.v[0, 0] - spin(sim, dim) * R) < 0.02 * abs(sim.p.v[0, 0])


def test_no_rolling_resistance_keeps_rolling():
    sim = rolling_ball(3, 0.0)
    sim.step(5000)
    assert sim.p.v[0, 0] == pytest.approx(V0, rel=1e-3)
    assert spin(sim, 3) * R == pytest.approx(V0, rel=1e-3)


def test_gravity_checked_and_2d_pairs_accepted():
    mat = ContactMaterial(E=1e8, nu=0.25, density=2650.0, friction=0.5, restitution=0.2)
    p = Particles.spheres([[0.0, R]], R, 2650.0, dim=2)
    assert np.array_equal(Simulation(p, mat, gravity=(0.0, -G)).gravity, [0.0, -G, 0.0])
    with pytest.raises(ValueError, match="gravity must be 3 finite numbers"):
        Simulation(p, mat, gravity=(0.0, -G, 0.0, 1.0))
    with pytest.raises(ValueError, match="gravity must be 3 finite numbers"):
        Simulation(p, mat, gravity=(0.0, np.nan, 0.0))
