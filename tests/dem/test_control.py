"""Dynamic relaxation and servo-controlled walls reach static equilibrium with the right forces."""

import pytest

from dem import ContactMaterial, Particles, Simulation, box_walls
from dem.bonded import hexagonal_lattice
from dem.control import ServoWall, relax, unbalanced_force_ratio

R, RHO, G = 1e-3, 2650.0, 9.81
# frictionless grains and walls: the base must carry exactly the weight (and the servo load)
MAT = ContactMaterial(E=1e6, nu=0.25, density=RHO, friction=0.0, restitution=0.5, law="linear",
                      kn=1e4, kt=0.0)


def column(top=False):
    x = hexagonal_lattice((0, 0), (0.02, 0.015), R)
    x[:, 1] += 1e-6
    p = Particles.spheres(x, R * 0.98, RHO, dim=2)
    walls = box_walls((-1e-4, 0, 0), (0.0201, 0.02, 0), dim=2, top=top)
    return Simulation(p, MAT, walls=walls, gravity=(0, -G, 0)), p


def test_relax_reaches_static_equilibrium():
    sim, p = column()
    info = relax(sim, tol=1e-5)
    assert unbalanced_force_ratio(sim) < 1e-5
    weight = float((p.mass * G).sum())
    base = [k for k in range(len(sim.walls)) if sim.walls.normal[k, 1] > 0.5][0]
    assert sim.walls.force[base, 1] == pytest.approx(-weight, rel=1e-3)
    assert sim.kinetic_energy().sum() < 1e-9 * weight * 0.01
    assert info["energy_removed"] > 0
    # the ledger books the relaxation's damping
    assert abs(sim.energy()["balance"]) < 1e-2 * info["energy_removed"]


def test_servo_wall_holds_the_confining_stress():
    sim, p = column(top=True)
    top = [k for k in range(len(sim.walls)) if sim.walls.normal[k, 1] < -0.5][0]
    base = [k for k in range(len(sim.walls)) if sim.walls.normal[k, 1] > 0.5][0]
    width = 0.0202
    servo = ServoWall(top, target=200.0, area=width, gain=2e-4, v_max=0.05)
    relax(sim, tol=1e-4, controllers=[servo], max_steps=400_000)
    assert servo.stress(sim) == pytest.approx(200.0, rel=1e-3)
    weight = float((p.mass * G).sum())
    assert sim.walls.force[base, 1] == pytest.approx(-(200.0 * width + weight), rel=2e-3)


def test_bad_controls_named():
    with pytest.raises(ValueError, match="ServoWall.gain"):
        ServoWall(0, 1.0, 1.0, -1.0, 1.0)
    sim, _ = column()
    with pytest.raises(RuntimeError, match="did not reach an unbalanced-force ratio"):
        relax(sim, tol=1e-12, max_steps=100)


def test_damped_steps_match_damping_between_single_steps():
    """`Simulation.step(n, decay=...)` (the damping inside the step loop, what `relax` runs)
    gives the bits of scaling the FREE velocities before each of n ``step(1)`` calls, and
    books the kinetic energy it takes out."""
    import numpy as np

    decay = 0.97
    a, pa = column()
    b, pb = column()
    for sim in (a, b):
        sim.step(200)   # falling and touching
    free = pb.kind == 0
    removed = 0.0
    for _ in range(60):
        ke = b.kinetic_energy().sum()
        pb.v[free] *= decay
        pb.omega[free] *= decay
        removed += ke - b.kinetic_energy().sum()
        b.step(1)
    a.step(60, decay=decay)
    np.testing.assert_array_equal(pa.x, pb.x)
    np.testing.assert_array_equal(pa.v, pb.v)
    assert a.damping_removed == pytest.approx(removed, rel=1e-12)
    ea, eb = a.energy(), b.energy()
    assert ea["dissipated_damping"] == pytest.approx(eb["dissipated_damping"] + removed, rel=1e-9)
    # the ledger closes as it does without damping (the same residual of the first 200 steps)
    assert ea["balance"] == pytest.approx(eb["balance"] + removed, abs=1e-9 * removed)
