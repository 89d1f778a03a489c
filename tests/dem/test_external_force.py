"""Constant external forces on particles (`Simulation.set_external_force`): a surcharge
carried to the floor, the ledger booking its work, and bad input named."""

import numpy as np
import pytest

from dem import GHOST, ContactMaterial, Particles, PlaneWall, Simulation, relax

MAT = ContactMaterial(E=1e7, nu=0.25, density=2650.0, friction=0.5, restitution=0.5, law="linear",
                      kn=1e6, kt=5e5)


def test_free_particle_under_a_constant_force_follows_the_closed_form():
    p = Particles.spheres(np.array([[0.0, 0.0, 0.0]]), np.array([1e-3]), 2650.0, dim=2)
    sim = Simulation(p, MAT, dt=1e-5)
    force = np.array([2e-3, -1e-3, 0.0])
    sim.set_external_force([0], force)
    sim.step(1000)
    t = sim.time
    a = force / p.mass[0]
    np.testing.assert_allclose(p.x[0], 0.5 * a * t**2, rtol=1e-10)
    en = sim.energy()
    np.testing.assert_allclose(en["work_external"], force @ p.x[0], rtol=1e-10)
    # (the shadow term at the start was taken before the force was set: dt^2 F^2 / 8m)
    assert abs(en["balance"]) < 1e-6 * en["work_external"]


def test_surcharge_on_a_column_reaches_the_floor_and_the_ledger_closes():
    """Three disks on a floor, a downward force on the top one, no gravity: once relaxed the
    floor carries exactly the surcharge, and the ledger balances with the surcharge's work."""
    r = 1e-3
    x = np.array([[0.0, r * (1 + 2 * k) * 1.001, 0.0] for k in range(3)])
    p = Particles.spheres(x, np.full(3, r), 2650.0, dim=2)
    sim = Simulation(p, MAT, walls=[PlaneWall((0, 0, 0), (0, 1, 0))])
    q = 50.0   # N per m thickness
    sim.set_external_force([2], (0.0, -q, 0.0))
    relax(sim, tol=1e-7)
    np.testing.assert_allclose(sim.walls.force[0], (0.0, -q, 0.0), rtol=1e-5, atol=1e-9)
    en = sim.energy()
    assert en["work_external"] > 0
    assert abs(en["balance"]) < 1e-3 * en["work_external"]
    # the state carries the ledger's external work across a restart
    state = sim.state_dict()
    again = Simulation(Particles.spheres(x, np.full(3, r), 2650.0, dim=2), MAT,
                       walls=[PlaneWall((0, 0, 0), (0, 1, 0))])
    again.set_external_force([2], (0.0, -q, 0.0))
    again.load_state(state)
    assert again.energy()["work_external"] == en["work_external"]


def test_the_state_carries_the_external_forces_across_a_restart():
    """`state_dict` holds the external forces set now (already in the force rows: a restart
    sets them beside the forces, not onto them); a fresh Simulation restored from it steps on
    to the bit, and a state without them (written before they were kept) leaves the ones set
    before `load_state`."""
    x = np.array([[0.0, 0.0, 0.0], [2.2e-3, 0.0, 0.0], [4.4e-3, 0.0, 0.0]])

    def build():
        return Simulation(Particles.spheres(x, np.full(3, 1.1e-3), 2650.0, dim=2), MAT, dt=1e-5)

    sim = build()
    sim.set_external_force([0, 2], [(1e-3, 0.0, 0.0), (-2e-3, 0.0, 0.0)])
    sim.step(300)
    state = sim.state_dict()
    sim.step(300)
    again = build()
    again.load_state(state)
    rows, f = again.external_force()
    assert rows.tolist() == [0, 2] and f[1, 0] == -2e-3
    again.step(300)
    assert np.array_equal(again.p.x, sim.p.x) and np.array_equal(again.p.v, sim.p.v)
    assert again.energy()["work_external"] == sim.energy()["work_external"]
    old = {k: v for k, v in state.items() if not k.startswith("external.")}
    other = build()
    other.set_external_force([1], (0.0, 1e-3, 0.0))
    other.load_state(old)
    assert other.external_force()[0].tolist() == [1]
    none = build()
    none.load_state(build().state_dict())
    assert len(none.external_force()[0]) == 0


def test_external_force_rejects_bad_rows_and_values():
    x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    p = Particles.spheres(x, np.full(2, 1e-3), 2650.0, dim=2, kind=np.array([0, GHOST], np.int8))
    sim = Simulation(p, MAT, dt=1e-5)
    with pytest.raises(ValueError, match="FREE"):
        sim.set_external_force([1], (0.0, 1.0, 0.0))
    with pytest.raises(ValueError, match=r"rows must lie in \[0, 2\)"):
        sim.set_external_force([5], (0.0, 1.0, 0.0))
    with pytest.raises(ValueError, match="not finite"):
        sim.set_external_force([0], (np.nan, 1.0, 0.0))
    with pytest.raises(ValueError, match=r"force\[:, 2\] must be 0"):
        sim.set_external_force([0], (0.0, 1.0, 1.0))
    sim.set_external_force([0], (0.0, 1.0, 0.0))
    assert p.force[0, 1] == 1.0
    sim.set_external_force(None, None)
    assert p.force[0, 1] == 0.0
    sim.step(10)
    assert p.v[0, 1] == 0.0


def test_default_time_step_is_known_before_the_simulation():
    from dem import default_time_step

    x = np.array([[0.0, 0.0, 0.0], [3e-3, 0.0, 0.0]])
    p = Particles.spheres(x, np.array([1e-3, 1.2e-3]), 2650.0, dim=2)
    dt = default_time_step(p, MAT)
    assert Simulation(p, MAT).dt == dt
    # a blow-up's state file goes to the temporary directory, not the working one
    import os
    import tempfile
    assert os.path.dirname(Simulation(p, MAT).state_path) == tempfile.gettempdir()
