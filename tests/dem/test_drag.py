"""Implicit group drag (`dem.drag`): exact terminal velocity and no overshoot at any
alpha dt / m (backward Euler on the half-step velocities), only the group mean dragged.

Tolerances: regression (1e-12) for what backward Euler gives exactly (the terminal velocity,
an untouched relative motion); the relaxation is checked for monotonicity, not a rate.
"""

import numpy as np
import pytest

from dem import ContactMaterial, Particles, Simulation
from dem.drag import GroupDrag, group_means

MAT = ContactMaterial(E=1e7, nu=0.25, density=2650.0, friction=0.3, restitution=0.5,
                      law="linear", kn=1e4, kt=5e3)


def two_grains(v):
    """Two disks far apart (no contact), velocities v (2, 2), no gravity."""
    x = np.array([[0.0, 0.0], [0.1, 0.0]])
    p = Particles.spheres(x, np.full(2, 1e-3), 2650.0, dim=2,
                          v=np.c_[np.asarray(v, float), np.zeros(2)])
    return Simulation(p, MAT, dt=1e-5)


@pytest.mark.parametrize("stiffness", [0.1, 100.0])
def test_terminal_velocity_is_exact(stiffness):
    """m dv/dt = F - alpha U: U -> F / alpha, exactly, for alpha dt / m small or large."""
    sim = two_grains([[0.0, 0.0], [0.0, 0.0]])
    m = sim.p.mass[0]
    alpha = stiffness * m / sim.dt
    F = np.array([1e-3, -2e-3, 0.0])
    sim.set_external_force([0, 1], F)
    drag = GroupDrag([0, 0], sim.p.radius**2, [alpha, alpha], np.zeros((1, 3)))
    sim.step(3000 if stiffness < 1 else 20, hook=drag.hook(sim))
    U = group_means(sim.p.v, np.zeros(2, np.int64), np.ones(2), 1)[0]
    np.testing.assert_allclose(U[:2], F[:2] / alpha, rtol=1e-9)


def test_no_overshoot_when_stiff():
    """A group coasting at 1 m/s against a drag 1000 times the step's: the velocity falls
    monotonically to the reference, never past it."""
    sim = two_grains([[1.0, 0.0], [1.0, 0.0]])
    sim.set_external_force([0, 1], np.zeros(3))
    alpha = 1000 * sim.p.mass[0] / sim.dt
    drag = GroupDrag([0, 0], [1.0, 1.0], [alpha, alpha], [[0.2, 0.0, 0.0]])
    last = 1.0
    for _ in range(10):
        sim.step(1, hook=drag.hook(sim))
        u = sim.p.v[0, 0]
        assert 0.2 <= u <= last
        last = u
    assert last == pytest.approx(0.2, abs=1e-6)


def test_only_the_group_mean_is_dragged():
    """Equal and opposite velocities in one group: the mean is the reference, no drag."""
    sim = two_grains([[1.0, 0.5], [-1.0, -0.5]])
    sim.set_external_force([0, 1], np.zeros(3))
    alpha = 100 * sim.p.mass[0] / sim.dt
    drag = GroupDrag([0, 0], [1.0, 1.0], [alpha, alpha], np.zeros((1, 3)))
    sim.step(5, hook=drag.hook(sim))
    np.testing.assert_allclose(sim.p.v[:, :2], [[1.0, 0.5], [-1.0, -0.5]], atol=1e-12)
    assert np.abs(drag.force).max() < 1e-12


def test_grains_out_of_contact_feel_the_drag():
    """Two grains in free flight (no contact, no other force) under gravity: the drag alone
    sets their terminal velocity m g / alpha (the kicks read the dragged rows)."""
    x = np.array([[0.0, 0.0], [0.1, 0.0]])
    sim = Simulation(Particles.spheres(x, np.full(2, 1e-3), 2650.0, dim=2), MAT, dt=1e-5,
                     gravity=(0.0, -9.81, 0.0))
    m = sim.p.mass[0]
    alpha = 0.1 * m / sim.dt
    drag = GroupDrag([0, 0], [1.0, 1.0], [alpha, alpha], np.zeros((1, 3)))
    sim.step(3000, hook=drag.hook(sim))
    np.testing.assert_allclose(sim.p.v[:, 1], -m * 9.81 / alpha, rtol=1e-9)


def test_bad_arrays_are_named():
    with pytest.raises(ValueError, match="weight and alpha"):
        GroupDrag([0, 0], [1.0], [1.0, 1.0], np.zeros((1, 3)))
    with pytest.raises(ValueError, match="reference means"):
        GroupDrag([0, 1], [1.0, 1.0], [1.0, 1.0], np.zeros((1, 3)))
    with pytest.raises(ValueError, match="alpha"):
        GroupDrag([0, 0], [1.0, 1.0], [1.0, -1.0], np.zeros((1, 3)))


def test_fused_loop_drags_as_the_hook():
    """``sim.step(n, drag=d)`` runs the drag inside the fused step loop: the same bits as the
    Python loop with ``hook=d.hook(sim)`` (the drag applied at the same point of a step), in
    a packing with contacts, walls, gravity and an external force, over neighbour builds."""
    from dem import box_walls
    from dem.packing import random_packing

    x, r = random_packing([0, 0], [0.02, 0.02], 0.9e-3, 1.1e-3, 0.4, seed=1)
    v0 = np.random.default_rng(2).normal(0, 0.05, (len(r), 2))
    group = (x[:, 1] // 0.005).astype(np.int64)

    def run(fused):
        p = Particles.spheres(x, r, 2650.0, dim=2, v=np.c_[v0, np.zeros(len(r))])
        sim = Simulation(p, MAT, walls=box_walls([0, 0, 0], [0.02, 1, 0], dim=2),
                         gravity=(0, -9.81))
        sim.set_external_force(np.arange(0, len(r), 3), [1e-4, -2e-4, 0.0])
        drag = GroupDrag(group, p.radius**2, np.full(len(r), 50 * p.mass.mean() / sim.dt),
                         np.full((group.max() + 1, 3), 1e-3))
        for _ in range(4):
            sim.step(150, drag=drag) if fused else sim.step(150, hook=drag.hook(sim))
        assert sim.nl.builds > 1
        return p.x.copy(), p.v.copy(), drag.force.copy(), sim.energy()

    a, b = run(True), run(False)
    for u, w in zip(a[:3], b[:3], strict=True):
        assert np.array_equal(u, w)
    assert a[3] == b[3]
