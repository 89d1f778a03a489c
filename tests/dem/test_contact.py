"""Contact laws against their formulas, friction regimes, time step and error handling,
determinism across thread counts and numba's disk cache."""

import math
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import dem
from dem.contact import P_ESTAR, P_GSTAR, pair_table
from dem.contact.hertz_mindlin import hertz_mindlin_force
from dem.contact.linear import linear_force

QUARTZ = dem.ContactMaterial(E=2.9e10, nu=0.25, density=2650.0, friction=0.5,
                             restitution=0.5)


def test_effective_moduli_match_peers():
    # /work/shared/peers/tools/params.py eff(): E* = 1.546667e10, G* = 3.314286e9 Pa
    row = pair_table([QUARTZ])[0, 0]
    assert row[P_ESTAR] == pytest.approx(2.9e10 / (2 * (1 - 0.25**2)), rel=1e-14)
    assert row[P_GSTAR] == pytest.approx(2.9e10 / (4 * 1.75 * 1.25), rel=1e-14)


def test_hertz_force_energy_and_damping():
    row = pair_table([QUARTZ])[0, 0]
    es, d, rs, ms, vn = row[P_ESTAR], 1e-6, 5e-4, 5e-6, 0.3
    fn, fnd, *_, e_n, e_pre, e_t, p_f, _ = hertz_mindlin_force(
        row, d, rs, ms, vn, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 1e-8)
    le = math.log(0.5)
    beta = le / math.sqrt(le**2 + math.pi**2)
    gn = -2 * math.sqrt(5 / 6) * beta * math.sqrt(2 * es * math.sqrt(rs * d) * ms)
    assert fn - fnd == pytest.approx(4 / 3 * es * math.sqrt(rs) * d**1.5, rel=1e-13)
    assert fnd == pytest.approx(gn * vn, rel=1e-13)
    assert e_n == pytest.approx(8 / 15 * es * math.sqrt(rs) * d**2.5, rel=1e-13)


def test_linear_static_and_dynamic_friction():
    """Seed 003 eq. 6: the limit is mu_s |fn| while sticking, mu_d |fn| once sliding."""
    mat = dem.ContactMaterial(E=1e7, nu=0.3, density=1000.0, friction=0.6,
                              friction_dynamic=0.4, restitution=1.0, law="linear",
                              kn=1e5, kt=1e5)
    row = pair_table([mat])[0, 0]
    delta, fn = 1e-5, 1.0  # kn delta = 1 N
    args = (row, delta, 1e-3, 1e-5, 0.0)

    def ft(s, slip):
        out = linear_force(*args, 0.0, 0.0, 0.0, s, 0.0, 0.0, slip, 1e-6)
        return out[2], out[11]

    assert ft(0.5e-5, 0) == pytest.approx((0.5, 0))   # elastic, sticking
    assert ft(0.59e-5, 0) == pytest.approx((0.59, 0))  # below mu_s
    assert ft(0.7e-5, 0) == pytest.approx((0.4 * fn, 1))  # breaks: dynamic limit
    assert ft(0.5e-5, 1) == pytest.approx((0.4 * fn, 1))  # keeps sliding above mu_d
    assert ft(0.3e-5, 1) == pytest.approx((0.3, 0))   # re-sticks below mu_d


def test_timestep_checks():
    p = dem.Particles.spheres([[0, 0, 0]], 1e-3, 2650.0)
    sim = dem.Simulation(p, QUARTZ)
    assert sim.dt_crit == pytest.approx(1.636805e-6, rel=1e-6)  # peers' Rayleigh step
    with pytest.raises(dem.TimeStepError, match="above the critical step"):
        dem.Simulation(p, QUARTZ, dt=2e-6)
    assert dem.Simulation(p, QUARTZ, dt=2e-6, force_dt=True).dt == 2e-6
    assert dem.hertz_dt(QUARTZ, 1e-3, p.mass[0], 1.0) > sim.dt_crit  # slow impacts: soft


def test_domain_and_blowup_errors(tmp_path):
    p = dem.Particles.spheres([[0, 0, 0]], 1e-3, 2650.0, v=[[1.0, 0, 0]])
    sim = dem.Simulation(p, QUARTZ, domain=([-1e-3] * 3, [1e-3] * 3), check_every=10)
    with pytest.raises(dem.DomainError, match="particle 0 left the domain"):
        sim.step(10000)
    p = dem.Particles.spheres([[0, 0, 0], [3e-3, 0, 0]], 1e-3, 2650.0)
    path = str(tmp_path / "last.npz")
    sim = dem.Simulation(p, QUARTZ, check_every=5, state_path=path)
    sim.step(5)
    p.v[1, 0] = np.nan  # a corrupted state, as from an unstable step
    with pytest.raises(dem.BlowUpError, match="last good state written") as err:
        sim.step(5)
    good = np.load(err.value.path)
    assert int(good["step"]) == 5 and np.isfinite(good["v"]).all()
    # a particle squeezed between two fixed ones (linear springs), integrated above the
    # stability limit sqrt(2 m / kn) of that oscillator
    lin = dem.ContactMaterial(E=1e7, nu=0.3, density=2650.0, friction=0.0, restitution=1.0,
                              law="linear", kn=1e4, kt=0.0)
    p = dem.Particles.spheres([[-1.99e-3, 0, 0], [0, 0, 0], [1.99e-3, 0, 0]], 1e-3, 2650.0,
                              v=[[0, 0, 0], [1e-3, 0, 0], [0, 0, 0]],
                              kind=[dem.FIXED, dem.FREE, dem.FIXED])
    dt = 1.5 * math.sqrt(2 * p.mass[1] / 1e4)
    sim = dem.Simulation(p, lin, dt=dt, force_dt=True, allow_overlap=True, state_path=path)
    with pytest.raises(dem.BlowUpError, match="kinetic energy jump"):
        sim.step(2000)
    assert sim.nsteps < 2000


SCRIPT = textwrap.dedent("""
    import sys, numpy as np, numba, dem
    numba.set_num_threads(int(sys.argv[1]))
    from dem import forces, integrate, neighbours, verlet
    forces.PARALLEL_MIN = integrate.KD_PARALLEL_MIN = 4096  # the prange drivers' defaults
    rng = np.random.default_rng(3)
    g = np.stack(np.meshgrid(*[np.arange(17)] * 3, indexing="ij"), -1).reshape(-1, 3)
    x = (g + 0.5) * 2.05e-3 + rng.uniform(-2e-5, 2e-5, g.shape)
    p = dem.Particles.spheres(x, 1e-3, 2650.0, v=rng.normal(0, 0.5, x.shape))
    mat = dem.ContactMaterial(E=2.9e7, nu=0.25, density=2650.0, friction=0.5,
                              restitution=0.5)
    sim = dem.Simulation(p, mat, dem.box_walls((0, 0, 0), (0.035,) * 3), (0, 0, -9.81))
    sim.step(60)
    np.save(sys.argv[2], np.concatenate([p.x, p.v, p.omega, p.force]))
    kernels = [forces._pair_rows_csr, forces._gather, forces.pair_layout, forces._wall_rows,
               forces._wall_scatter,
               verlet._drift, verlet._kick, verlet._kick_drift_par,
               neighbours._pairs]
    print(sum(sum(k.stats.cache_misses.values()) for k in kernels),
          min(sum(k.stats.cache_hits.values()) for k in kernels), len(sim.nl.pi))
""")


def test_cache_and_thread_determinism(tmp_path):
    """A second process loads every kernel from numba's disk cache (no compilation), and
    1 and 2 threads give bit-identical states (4913 particles: serial kernels on 1 thread,
    the parallel drivers of pairs, walls and kick-drift on 2)."""
    script = tmp_path / "run.py"
    script.write_text(SCRIPT)
    env = dict(os.environ, PYTHONPATH=os.getcwd())
    res = []
    for threads in (1, 2, 2):
        out = subprocess.run([sys.executable, str(script), str(threads),
                              str(tmp_path / f"s{threads}.npy")], env=env, check=True,
                             capture_output=True, text=True, cwd=os.getcwd())
        res.append([int(a) for a in out.stdout.split()])
    misses, hits, npairs = res[-1]
    assert misses == 0 and hits >= 1 and npairs > 4096  # hits: of every kernel
    assert np.array_equal(np.load(tmp_path / "s1.npy"), np.load(tmp_path / "s2.npy"))


def test_ghost_particles_prescribed_and_reporting_forces():
    """A GHOST keeps the motion written from outside, yet carries its contact force (the
    coupling reads it); re-evaluating forces without history update is repeatable."""
    p = dem.Particles.spheres([[0, 0, 0], [1.999e-3, 0, 0]], 1e-3, 2650.0,
                              v=[[0.01, 0.002, 0], [0, 0, 0]], kind=[dem.GHOST, dem.FREE])
    sim = dem.Simulation(p, QUARTZ, allow_overlap=True)
    for k in range(1, 11):
        p.x[0] = k * sim.dt * p.v[0]  # the prescribed motion, written from outside
        sim.step(1)
    assert np.array_equal(p.x[0], 10 * sim.dt * p.v[0])  # ghosts are not integrated
    assert p.force[0, 0] < 0 and np.allclose(p.force[0], -p.force[1], rtol=1e-12)
    assert p.v[1, 0] > 0  # the free particle was pushed
    hist = sim.nl.hist.copy()
    sim.compute_forces(update_history=False)
    f = p.force.copy()
    sim.compute_forces(update_history=False)  # idempotent: a staggered re-evaluation
    assert np.array_equal(sim.nl.hist, hist) and np.array_equal(p.force, f)
    en = sim.energy()  # the ghost pushes: work on the free particle, booked exactly
    assert en["work_ghosts"] > 0
    assert abs(en["balance"]) < 1e-3 * (en["initial"] + en["work_ghosts"])  # dt = 0.2 dt_R
