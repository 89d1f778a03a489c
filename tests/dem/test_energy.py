"""Energy: an elastic frictionless assembly conserves energy; with damping and friction the
ledger (kinetic + elastic + dissipated - work of gravity) closes and converges with dt."""

import numpy as np
import pytest

import dem

R, L = 1.0e-3, 5.0e-3


def box_of_eight(law="hertz_mindlin", mu=0.0, e=1.0, safety=None, gravity=(0, 0, 0)):
    """8 spheres (E = 2.9e8 Pa) in a closed 5 mm box, random velocities ~1 m/s and spins."""
    kw = dict(kn=2e4, kt=1.6e4) if law == "linear" else {}
    mat = dem.ContactMaterial(E=2.9e8, nu=0.25, density=2650.0, friction=mu, restitution=e,
                              law=law, **kw)
    rng = np.random.default_rng(4)
    g = np.stack(np.meshgrid(*[np.arange(2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    x = (g + 0.5) * (L / 2) + rng.uniform(-1e-4, 1e-4, (8, 3))
    p = dem.Particles.spheres(x, R, 2650.0, v=rng.normal(0, 1.0, (8, 3)),
                              omega=rng.normal(0, 300.0, (8, 3)))
    walls = dem.box_walls((0, 0, 0), (L, L, L), top=True)
    return dem.Simulation(p, mat, walls, gravity, safety=safety)


def ledger_history(sim, steps, samples=20):
    bal = []
    for _ in range(samples):
        sim.step(steps // samples)
        en = sim.energy()
        bal.append(en["balance"] / en["initial"])
    return np.array(bal), sim.energy()


def test_elastic_frictionless_energy_drift():
    """1e5 steps at dt = 0.003 dt_R: |E(t) - E(0)| / E(0) < 1e-6 at every sample, with
    dozens of collisions. Velocity Verlet is symplectic, but each Hertz contact onset (F ~
    delta^1.5, not smooth at 0) leaves an energy error that falls fast with dt: 1.7e-4 per
    impact at 0.2 dt_R, 3e-8 at 0.02 dt_R (peers RESULTS.md §2); this box measured 6e-7 at
    0.003 dt_R and 1e-5 at 0.02 dt_R."""
    sim = box_of_eight(safety=0.003, gravity=(0, 0, -9.81))
    bal, en = ledger_history(sim, 100_000)
    assert sim.nl.builds > 100  # particles really move and collide
    assert en["dissipated_damping"] == en["dissipated_friction"] == 0.0
    assert np.abs(bal).max() < 1e-6


@pytest.mark.parametrize("law, safeties", [("linear", (0.02, 0.01)),
                                            ("hertz_mindlin", (0.04, 0.02))])
def test_ledger_closes_with_damping_and_friction(law, safeties):
    """Damping (e = 0.5) and friction (mu = 0.5) dissipate most of the energy; the
    ledger closes to < 5e-4 of it and the residual falls with dt (second order-ish)."""
    res = []
    for s in safeties:
        bal, en = ledger_history(box_of_eight(law, 0.5, 0.5, s, (0, 0, -9.81)), 50_000)
        assert en["dissipated_damping"] > 0.3 * en["initial"]
        assert en["dissipated_friction"] > 0.05 * en["initial"]
        assert en["work_gravity"] > 0
        res.append(np.abs(bal).max())
    assert res[0] < 5e-4
    assert res[1] < res[0] / 2.5
