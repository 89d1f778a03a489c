"""The drivers of the contact pass on dense packings (grains in lasting contact): the
compact-layout loop (`_pair_csr`, what a serial step runs), the plain fused loop, the rows
written for the threads and summed by `_scatter` or `_gather`, and the wall loop against
its rows form give the same bits, with two materials, rolling resistance, static and
dynamic friction; one contact assembled from the law functions by hand equals the pass."""

import numpy as np
import pytest

import dem
from dem import forces
from dem.contact import HIST, pair_table
from dem.contact.hertz_mindlin import hertz_mindlin_force
from dem.contact.kinematics import pair_kinematics, project_history
from dem.contact.linear import linear_force
from dem.packing import lattice_packing


def dense_sim(dim, seed=4):
    """A bed of touching grains after some settling: many contacts sliding or sticking."""
    rng = np.random.default_rng(seed)
    if dim == 3:
        g = np.stack(np.meshgrid(*[np.arange(7)] * 3, indexing="ij"), -1).reshape(-1, 3)
        x = (g + 0.5) * 2.0e-3 + rng.uniform(-2e-6, 0.0, g.shape)
        mats = [dem.ContactMaterial(E=2.9e7, nu=0.25, density=2650.0, friction=0.5,
                                    restitution=0.5, limit_force=True, rolling_friction=0.05),
                dem.ContactMaterial(E=5e7, nu=0.3, density=2650.0, friction=0.3,
                                    friction_dynamic=0.2, restitution=0.7, limit_force=True)]
        walls = dem.box_walls((0, 0, 0), (14e-3,) * 3)
        r, gravity = 1e-3, (0, 0, -9.81)
    else:
        x, _ = lattice_packing((0, 0), (0.05, 0.05), 1.5e-3, kind="hex")
        x[:, :2] += rng.uniform(-3e-6, 0.0, (len(x), 2))
        mats = [dem.ContactMaterial(E=1e8, nu=0.25, density=2650.0, friction=0.5,
                                    restitution=0.5, law="linear", kn=2e5, kt=1e5,
                                    rolling_friction=0.1),
                dem.ContactMaterial(E=1e8, nu=0.25, density=2650.0, friction=0.4,
                                    friction_dynamic=0.3, restitution=0.3, law="linear",
                                    kn=3e5, kt=1.5e5)]
        walls = dem.box_walls((0, 0, 0), (0.05, 0.05, 0), dim=2)
        r, gravity = 1.5e-3, (0, -9.81, 0)
    v = rng.normal(0, 0.05, x.shape)
    om = rng.normal(0, 20.0, x.shape)
    if dim == 2:
        v[:, 2] = 0.0
        om[:, :2] = 0.0
    p = dem.Particles.spheres(x, r, 2650.0, dim=dim, v=v, omega=om,
                              material=rng.integers(0, 2, len(x)))
    sim = dem.Simulation(p, mats, walls, gravity, allow_overlap=True)
    sim.step(150)
    return sim


def pass_with(sim, path):
    """One contact pass over the current state through one driver; copies of the history
    are updated, so every driver starts from the same state. Returns all outputs."""
    p, nl = sim.p, sim.nl
    hist, slip, etan = nl.hist.copy(), nl.slip.copy(), nl.etan.copy()
    acc = [np.zeros((p.n, 3)) for _ in range(5)]
    hit = np.zeros(p.n, np.int8)
    out = np.full((len(nl.pi) + 1, forces.NOUT), np.nan)
    args = (nl.pi, nl.pj, p.x, p.v, p.omega, p.radius, p.mass, p.material, sim.table, hist,
            slip, etan, sim.dt)
    hp = 0.5 * sim.dt  # the dashpots' prediction, as in a step
    if path == "csr":
        lay = forces.pair_layout(nl.pi, nl.pj, p.n, hist, slip, etan)
        e = forces.pair_forces(*args, out, *acc, hit=hit, layout=lay, horizon=hp)
    elif path == "fused":
        e = forces.pair_forces(*args, out, *acc, hit=hit, horizon=hp)
    elif path == "rows":
        e = forces.pair_forces(*args, out, *acc, hit=hit, rows=True, horizon=hp)
    elif path == "rows_csr":
        lay = forces.pair_layout(nl.pi, nl.pj, p.n, hist, slip, etan)
        e = forces.pair_forces(*args, out, *acc, hit=hit, rows=True, layout=lay, horizon=hp)
    else:  # the threads' path: rows over the layout, then the per-particle gather
        start, pj32, live, jstart, jrow = forces.pair_layout(nl.pi, nl.pj, p.n, hist, slip,
                                                             etan)
        touched = np.zeros(p.n, np.int8)
        forces._pair_rows_csr(start, pj32, live, *args[2:], hp, out, touched)
        part = np.zeros(((p.n + forces.GATHER_CHUNK - 1) // forces.GATHER_CHUNK, 2))
        forces._gather(start, jstart, jrow, live, out, *acc, hit, part, touched)
        e = (float(part[:, 0].sum()), float(part[:, 1].sum()))
    return [np.asarray(e), *acc, hit, hist, slip, etan]


@pytest.mark.parametrize("dim", [2, 3])
def test_pair_drivers_agree_to_the_bit_on_dense_beds(dim):
    sim = dense_sim(dim)
    p, nl = sim.p, sim.nl
    touching = len(sim.contacts()[0])
    assert touching > p.n  # lasting contacts: more than one per grain
    ref0 = pass_with(sim, "csr")
    assert (ref0[-2] == 1).any() and (ref0[-2] == 0).any()  # sliding and sticking contacts
    for path in ("fused", "rows", "rows_csr", "gather"):
        ref, got = ref0, pass_with(sim, path)
        if path == "gather":  # energies summed by chunks of particles
            np.testing.assert_allclose(got[0], ref[0], rtol=1e-12)
            ref, got = ref[1:], got[1:]
        for a, b in zip(ref, got, strict=True):
            assert np.array_equal(a, b), path
    assert nl.builds >= 1


@pytest.mark.parametrize("dim", [2, 3])
def test_wall_rows_equal_the_serial_wall_loop(dim):
    sim = dense_sim(dim)
    p, nl, w = sim.p, sim.nl, sim.walls
    res = []
    for rows in (False, True):
        hist, slip, etan = nl.whist.copy(), nl.wslip.copy(), nl.wetan.copy()
        acc = [np.zeros((p.n, 3)) for _ in range(5)]
        hit = np.zeros(p.n, np.int8)
        wf = np.zeros((len(w), 9))
        out = np.full((len(nl.wi) + 1, forces.NOUT), np.nan)
        args = (nl.wi, nl.ww, p.x, p.v, p.omega, p.radius, p.mass, p.material, w.point,
                w.normal, w.velocity, w.material, sim.table, hist, slip, etan, sim.dt)
        if rows:
            forces._wall_rows(*args, 0.5 * sim.dt, out)
            e = forces._wall_scatter(nl.wi, nl.ww, out, *acc, wf, hit)
        else:
            e = forces.wall_forces(*args, out, *acc, wf, hit=hit, horizon=0.5 * sim.dt)
        res.append([np.asarray(e), *acc, hit, wf, hist, slip, etan])
    assert (res[0][-1] != 0).sum() > 10  # walls carry the bed
    for a, b in zip(*res, strict=True):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("law", ["hertz_mindlin", "linear"])
def test_one_contact_equals_the_law_assembled_by_hand(law):
    """Force, torques, damping and energies of one pair from `pair_forces` equal the
    law's outputs put together as the module docstring of `dem.forces` states."""
    kw = dict(kn=2e5, kt=1e5) if law == "linear" else {}
    mat = dem.ContactMaterial(E=2.9e7, nu=0.25, density=2650.0, friction=0.3,
                              restitution=0.5, law=law, rolling_friction=0.02, **kw)
    x = np.array([[0.0, 0.0, 0.0], [1.7e-3, 0.6e-3, -0.3e-3]])
    v = np.array([[0.02, -0.01, 0.005], [-0.01, 0.0, 0.003]])
    om = np.array([[3.0, -2.0, 1.0], [0.5, 4.0, -1.5]])
    radius, mass = np.array([1e-3, 0.9e-3]), np.array([1.1e-5, 0.8e-5])
    table = pair_table([mat])
    # spring [m], normal force [N] and speed [m/s] of the last pass (the dashpot's history)
    hist = np.array([[1e-6, -2e-6, 0.5e-6, 3e-3, 0.015, 0.0]])
    assert hist.shape[1] == HIST
    slip, etan = np.zeros(1, np.int8), np.zeros(1)
    pi, pj = np.array([0]), np.array([1])
    acc = [np.zeros((2, 3)) for _ in range(5)]
    out = np.zeros((1, forces.NOUT))
    h0 = hist.copy()
    e, es = forces.pair_forces(pi, pj, x, v, om, radius, mass, np.zeros(2, np.int32), table,
                               hist, slip, etan, 1e-6, out, *acc, horizon=0.5e-6)
    nx, ny, nz, delta, reff, meff, vn, vtx, vty, vtz, ai, aj = pair_kinematics(
        x, v, om, radius, mass, 0, 1)
    n = np.array([nx, ny, nz])
    s = project_history(*h0[0, :3], nx, ny, nz)
    f = (linear_force if law == "linear" else hertz_mindlin_force)(
        table[0, 0], delta, reff, meff, vn, vtx, vty, vtz, *s, 0, 1e-6, 3e-3, 0.015, 0.0, 0.5e-6)
    fn, fnd, ft, fd, s_new, e_n, e_t = f[0], f[1], np.array(f[2:5]), np.array(f[5:8]), \
        np.array(f[8:11]), f[12], f[14]
    wr = om[0] - om[1]
    mr = 0.02 * abs(fn) * reff / np.linalg.norm(wr)
    force, torque, fe, fdamp, tdamp = acc
    np.testing.assert_allclose(force[1], fn * n + ft, rtol=1e-14)
    np.testing.assert_allclose(force[0], -(fn * n + ft), rtol=1e-14)
    np.testing.assert_allclose(torque[0], -ai * np.cross(n, ft) - mr * wr, rtol=1e-13)
    np.testing.assert_allclose(torque[1], -aj * np.cross(n, ft) + mr * wr, rtol=1e-13)
    np.testing.assert_allclose(fe[1], (fn - fnd) * n, rtol=1e-14)
    np.testing.assert_allclose(fdamp[1], fnd * n + fd, rtol=1e-14)
    np.testing.assert_allclose(tdamp[0], -ai * np.cross(n, fd), rtol=1e-13, atol=1e-30)
    np.testing.assert_allclose(hist[0, :3], s_new, rtol=1e-14)
    assert tuple(hist[0, 3:]) == (fn, vn, f[16])  # the next pass's dashpot history
    assert e == pytest.approx(e_n + e_t, rel=1e-14) and es == pytest.approx(e_t, rel=1e-14)
    assert etan[0] == es


def test_coincident_centres_give_no_force():
    """Two grains at one point (no normal): every driver returns zero forces and the
    overlap's energy, as before the scalar contact path."""
    mat = dem.ContactMaterial(E=1e7, nu=0.25, density=1000.0, friction=0.5, restitution=0.5,
                              law="linear", kn=1e5, kt=5e4)
    x = np.zeros((2, 3))
    v = np.array([[0.1, 0.0, 0.0], [0.0, 0.0, 0.0]])
    radius, mass = np.full(2, 1e-3), np.full(2, 1e-5)
    res = []
    for rows in (False, True):
        hist, slip, etan = np.zeros((1, HIST)), np.zeros(1, np.int8), np.zeros(1)
        acc = [np.zeros((2, 3)) for _ in range(5)]
        e = forces.pair_forces(np.array([0]), np.array([1]), x, v, np.zeros((2, 3)), radius,
                               mass, np.zeros(2, np.int32), pair_table([mat]), hist, slip,
                               etan, 1e-6, np.zeros((1, forces.NOUT)), *acc, rows=rows)
        assert not np.any([a.any() for a in acc])
        assert e[0] == pytest.approx(0.5 * 1e5 * (2e-3) ** 2)
        res.append(e)
    assert res[0] == res[1]
