"""The fast paths of the serial engine give the same bits as the plain ones: the compact
pair layout with live flags (dem.forces.pair_layout) against the plain fused loop, the
kick + next drift pass (`_kick_drift`, sparse in the force rows) against step(1) calls,
and contact history written from outside between two calls of `step`."""

import numpy as np

import dem


def scene(seed=3, n_side=9):
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(*[np.arange(n_side)] * 3, indexing="ij"), -1).reshape(-1, 3)
    x = (g + 0.5) * 2.05e-3 + rng.uniform(-2e-5, 2e-5, g.shape)
    p = dem.Particles.spheres(x, 1e-3, 2650.0, v=rng.normal(0, 0.5, x.shape),
                              omega=rng.normal(0, 100.0, x.shape))
    mat = dem.ContactMaterial(E=2.9e7, nu=0.25, density=2650.0, friction=0.5,
                              restitution=0.5, limit_force=True)
    walls = dem.box_walls((0, 0, 0), (n_side * 2.05e-3,) * 3)
    return dem.Simulation(p, mat, walls, (0, 0, -9.81), check_every=37)


def state(sim):
    p = sim.p
    return np.concatenate([p.x, p.v, p.omega, p.force, p.torque])


def advance(fast, plain, n):
    """n steps: in one call (fused kick + drift) and in n calls of one step."""
    fast.step(n)
    for _ in range(n):
        plain.step(1)


def test_layout_and_fused_kick_drift_match_plain_paths(monkeypatch):
    fast = scene()
    fast.step(300)
    assert fast.nl.builds > 2 and len(fast.contacts()[0]) > 10
    plain = scene()
    monkeypatch.setattr(dem.Simulation, "_layout", lambda self, fresh: None)
    for _ in range(300):
        plain.step(1)
    assert np.array_equal(state(fast), state(plain))
    assert np.array_equal(fast.nl.hist, plain.nl.hist)
    assert np.array_equal(fast.nl.slip, plain.nl.slip)
    ef, ep = fast.energy(), plain.energy()
    for k in ef:
        assert abs(ef[k] - ep[k]) <= 1e-12 * (abs(ef["initial"]) + abs(ef[k])), k


def test_history_written_between_steps_is_seen():
    """Contact history written in place from outside between two calls of `step` (as a
    restart may do) is seen by the fast path: a spring put on every candidate pair, open or
    not, is released or used exactly as by the plain path."""
    a, b = scene(), scene()
    b._layout = lambda fresh: None
    advance(a, b, 150)
    for sim in (a, b):
        sim.nl.hist[:] = 1e-9
    advance(a, b, 100)
    assert np.array_equal(state(a), state(b))
    assert np.array_equal(a.nl.hist, b.nl.hist)


def test_compute_forces_between_steps():
    """A history-free re-evaluation between steps (staggered coupling) acts the same on the
    fast and the plain paths (it leaves the history alone and the next drift uses its
    forces)."""
    a, b = scene(), scene()
    b._layout = lambda fresh: None
    advance(a, b, 120)
    for sim in (a, b):
        sim.compute_forces(update_history=False)
    advance(a, b, 80)
    assert np.array_equal(state(a), state(b))
