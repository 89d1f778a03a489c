"""Energy: an elastic frictionless assembly conserves energy; with damping, friction, gravity
and a moving wall the ledger (kinetic - shadow + elastic + dissipated - work) closes to
round-off where the forces are linear in the positions, and otherwise to the time error
of the conservative normal forces alone (below 1e-6 at a small step, falling as dt^2)."""

import numpy as np
import pytest

import dem

R, L = 1.0e-3, 5.0e-3


def box_of_eight(law="hertz_mindlin", mu=0.0, e=1.0, safety=None, gravity=(0, 0, 0),
                 wall_speed=0.0):
    """8 spheres (E = 2.9e8 Pa) in a closed 5 mm box, random velocities ~1 m/s and spins;
    the lid moves down at ``wall_speed`` [m/s]."""
    kw = dict(kn=2e4, kt=1.6e4) if law == "linear" else {}
    mat = dem.ContactMaterial(E=2.9e8, nu=0.25, density=2650.0, friction=mu, restitution=e,
                              law=law, **kw)
    rng = np.random.default_rng(4)
    g = np.stack(np.meshgrid(*[np.arange(2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    x = (g + 0.5) * (L / 2) + rng.uniform(-1e-4, 1e-4, (8, 3))
    p = dem.Particles.spheres(x, R, 2650.0, v=rng.normal(0, 1.0, (8, 3)),
                              omega=rng.normal(0, 300.0, (8, 3)))
    walls = dem.box_walls((0, 0, 0), (L, L, L), top=True)
    sim = dem.Simulation(p, mat, walls, gravity, safety=safety)
    sim.walls.velocity[-1] = (0.0, 0.0, -wall_speed)
    return sim


def scale(en):
    """Energy scale [J]: what was there at the start plus what was put in."""
    return en["initial"] + abs(en["work_walls"]) + abs(en["work_gravity"])


def ledger_history(sim, steps, samples=20):
    bal = []
    for _ in range(samples):
        sim.step(steps // samples)
        en = sim.energy()
        bal.append(en["balance"] / scale(en))
    return np.array(bal), sim.energy()


def test_elastic_frictionless_energy_drift():
    """1e5 steps at dt = 0.0025 dt_R: |E(t) - E(0)| / E(0) < 1e-6 at every sample, with
    dozens of collisions. Velocity Verlet is symplectic, but each Hertz contact onset (F ~
    delta^1.5, not smooth at 0) leaves an energy error that falls fast with dt: 1.7e-4 per
    impact at 0.2 dt_R, 3e-8 at 0.02 dt_R (peers RESULTS.md §2); this box measured 1e-6 at
    0.003 dt_R and 1e-5 at 0.02 dt_R."""
    sim = box_of_eight(safety=0.0025, gravity=(0, 0, -9.81))
    bal, en = ledger_history(sim, 100_000)
    assert sim.nl.builds > 80  # particles really move and collide
    assert en["dissipated_damping"] == en["dissipated_friction"] == 0.0
    assert np.abs(bal).max() < 1e-6


def test_ledger_exact_for_forces_linear_in_positions():
    """A sphere squeezed between the floor and a lid that moves down and sideways (linear
    springs, damping e = 0.5, sliding and sticking friction 0.5, gravity, spin): every
    contact force is linear in the positions, so the trapezoidal work is the exact change
    of the elastic energy and the ledger closes to round-off at every step."""
    mat = dem.ContactMaterial(E=1e8, nu=0.25, density=2650.0, friction=0.5, restitution=0.5,
                              law="linear", kn=2e4, kt=1.6e4)
    d0 = 2e-5  # initial overlap at both walls [m]: 0.4 N, far above the motion's forces
    p = dem.Particles.spheres([[0, 0, R - d0]], R, 2650.0, v=[[0.5, -0.2, 0.005]],
                              omega=[[0.0, 3000.0, 500.0]])  # slides at first, then rolls
    walls = [dem.PlaneWall((0, 0, 0), (0, 0, 1)),
             dem.PlaneWall((0, 0, 2 * R - 2 * d0), (0, 0, -1), velocity=(0.01, 0, -1e-4))]
    sim = dem.Simulation(p, mat, walls, (0, 0, -9.81), allow_overlap=True)
    worst = 0.0
    slid = stuck = False
    for _ in range(2000):
        sim.step(2)
        en = sim.energy()
        worst = max(worst, abs(en["balance"]) / scale(en))
        slid |= bool(sim.nl.wslip.any())
        stuck |= bool((sim.nl.wslip == 0).any())
    assert len(sim.contacts()[0]) == 0 and (sim.nl.wetan > 0).all()  # both walls touch
    assert slid and stuck
    assert en["dissipated_damping"] > 0 and en["dissipated_friction"] > 0
    assert en["work_walls"] != 0 and en["work_gravity"] != 0
    assert worst < 1e-11


def test_ledger_closes_with_damping_friction_gravity_moving_wall():
    """Hertz-Mindlin, restitution 0.5, friction 0.5, gravity, the lid moving in: damping
    and friction take most of the energy, and the ledger closes to < 1e-6 of the energy
    scale over 6e4 steps (the time error of the Hertz normal forces, as in the elastic
    case: 1.2e-6 at 0.004 dt_R, 7e-7 at 0.003 dt_R)."""
    sim = box_of_eight("hertz_mindlin", 0.5, 0.5, 0.003, (0, 0, -9.81), wall_speed=0.02)
    bal, en = ledger_history(sim, 60_000, samples=30)
    assert en["dissipated_damping"] > 0.5 * en["initial"]
    assert en["dissipated_friction"] > 0.1 * en["initial"]
    assert en["work_gravity"] > 0 and en["work_walls"] > 0
    assert np.abs(bal).max() < 1e-6


@pytest.mark.parametrize("law, safeties", [("linear", (0.02, 0.01)),
                                            ("hertz_mindlin", (0.04, 0.02))])
def test_ledger_residual_is_a_time_error(law, safeties):
    """What is left falls with dt like a second-order time error (~4x per halving)."""
    res = []
    for s in safeties:
        steps = int(400 / s)
        bal, en = ledger_history(box_of_eight(law, 0.5, 0.5, s, (0, 0, -9.81), 0.02), steps)
        assert en["dissipated_damping"] > 0.3 * en["initial"]
        res.append(np.abs(bal).max())
    assert res[1] < res[0] / 2.5
