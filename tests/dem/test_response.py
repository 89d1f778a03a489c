"""A force linear in the displacement through a sparse solve (`dem.response`): the kernel
equals scipy's products and SuperLU's solve; in `Simulation.step` the fused loop and the
Python loop give the same bits with it and with pauses between steps; a linear spring
built from it oscillates at its closed-form frequency.

Tolerances: 1e-12 relative against scipy (round-off of a different summation order);
bit equality between the loops (the same kernels in the same order)."""

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import splu

import dem
from dem.response import LinearResponse
from dem.state import GHOST
from tests.dem.test_fused_steps import counted, same, scene


def random_response(rows, x_ref, nb=40, seed=0, nn=None):
    """A response of random sparse operators; with nn: through a random basis of nn nodes
    (3 a particle, some -1). Returns it and (A, S, T, r) with S, T on the particles."""
    rng = np.random.default_rng(seed)
    m, d = x_ref.shape
    A = (sp.random(nb, nb, density=0.15, random_state=rng) + 4.0 * sp.identity(nb)).tocsc()
    r = rng.normal(size=nb) * 1e-6
    if nn is None:
        S = sp.random(nb, m * d, density=0.2, random_state=rng) * 1e-2
        T = sp.random(m * d, nb, density=0.2, random_state=rng) * 1e-3
        return LinearResponse(rows, x_ref, S, r, splu(A), T), (A, S, T, r)
    S = sp.random(nb, nn * d, density=0.2, random_state=rng) * 1e-2
    T = sp.random(nn * d, nb, density=0.2, random_state=rng) * 1e-3
    nodes = rng.integers(-1, nn, (m, 3))
    to, fro = rng.uniform(0, 1, (m, 3)), rng.uniform(0, 1, (m, 3))
    G, H = sp.lil_matrix((nn * d, m * d)), sp.lil_matrix((m * d, nn * d))
    for k in range(m):
        for a in range(3):
            if nodes[k, a] >= 0:
                for c in range(d):
                    G[nodes[k, a] * d + c, k * d + c] += to[k, a]
                    H[k * d + c, nodes[k, a] * d + c] += fro[k, a]
    resp = LinearResponse(rows, x_ref, S, r, splu(A), T, basis=(nodes, to, fro))
    return resp, (A, S @ G, H @ T, r)


@pytest.mark.parametrize("nn", [None, 30])
def test_kernel_equals_scipy(nn):
    sim = scene(2)
    rows = np.arange(0, sim.p.n, 3)
    x_ref = sim.p.x[rows, :2] - 1e-4
    resp, (A, S, T, r) = random_response(rows, x_ref, nn=nn)
    sim.p.kind[rows[1]] = GHOST     # a GHOST row takes none of it
    before = sim.p.force.copy()
    for k in (1, 2, 3):
        resp.apply(sim)
        u = (sim.p.x[rows, :2] - x_ref).ravel()
        f = (T @ splu(A).solve(S @ u - k * r)).reshape(-1, 2)
        f[1] = 0.0
        np.testing.assert_allclose(resp.force[:, :2], f, rtol=1e-12, atol=1e-12 * abs(f).max())
        assert resp.count[0] == k
    assert np.array_equal(sim.p.force[rows[1]], before[rows[1]])
    resp.withdraw(sim)
    assert not resp.force.any()


@pytest.mark.parametrize("pause_every", [0, 7])
def test_fused_loop_equals_python_loop(pause_every, monkeypatch):
    """The response applied every step and, every pause_every steps, a pause that withdraws
    its force and takes a new reference (as a fluid step does): the same bits either way."""
    calls = counted(monkeypatch)
    fused, loop = scene(2), scene(2)
    rows = np.arange(fused.p.n)
    pauses = {id(fused): [], id(loop): []}

    def set_up(sim):
        resp, _ = random_response(rows, sim.p.x[rows, :2], nb=60, seed=3, nn=100)

        def pause():
            pauses[id(sim)].append(sim.nsteps)
            resp.withdraw(sim)
            resp.reset(sim.p.x[rows, :2])
        return resp, pause

    (rf, pf), (rl, pl) = set_up(fused), set_up(loop)
    for n in (1, 150, 63, 2):
        assert fused.step(n, response=rf, pause_every=pause_every, pause=pf) == n
        assert loop.step(n, hook=lambda: False, response=rl, pause_every=pause_every, pause=pl) == n
        same(fused, loop)
        assert np.array_equal(rf.force, rl.force) and rf.count[0] == rl.count[0]
    assert len(calls) > fused.nl.builds
    assert pauses[id(fused)] == pauses[id(loop)]
    # a pause after every 7th step of a call, not after the call's last step
    expected = [] if not pause_every else [
        start + k for start, n in ((1, 150), (151, 63), (214, 2)) for k in range(7, n, 7)]
    assert pauses[id(fused)] == expected
    assert abs(rf.force).max() > 0


def test_a_spring_oscillates_at_its_frequency():
    """S = I, A = I, T = -k I: f = -k (x - x_ref), a free disk oscillates at sqrt(k / m)."""
    p = dem.Particles.spheres(np.array([[0.0, 0.0]]), 1e-3, 2650.0, dim=2, v=np.array([[1e-3, 0, 0]]))
    mat = dem.ContactMaterial(E=1e7, nu=0.25, density=2650.0, friction=0.3, restitution=0.5,
                              law="linear", kn=1e4, kt=5e3)
    sim = dem.Simulation(p, mat, dt=1e-5)
    m, k = sim.p.mass[0], 50.0
    omega = np.sqrt(k / m)
    I2 = sp.identity(2, format="csc")
    resp = LinearResponse([0], sim.p.x[:1, :2], I2, np.zeros(2), splu(I2), -k * I2)
    n = int(round(2 * np.pi / omega / sim.dt))
    xs = []
    for _ in range(n):
        sim.step(1, response=resp)
        xs.append(sim.p.x[0, 0])
    t = sim.dt * np.arange(1, n + 1)
    np.testing.assert_allclose(xs, 1e-3 / omega * np.sin(omega * t), atol=1e-3 / omega * 1e-3)


def spring(k=50.0, stride=1, dt=1e-5):
    """A free disk on the response S = A = I, T = -k I (f = -k (x - x_ref)) at 1 mm/s."""
    p = dem.Particles.spheres(np.array([[0.0, 0.0]]), 1e-3, 2650.0, dim=2, v=np.array([[1e-3, 0, 0]]))
    mat = dem.ContactMaterial(E=1e7, nu=0.25, density=2650.0, friction=0.3, restitution=0.5,
                              law="linear", kn=1e4, kt=5e3)
    sim = dem.Simulation(p, mat, dt=dt)
    I2 = sp.identity(2, format="csc")
    return sim, LinearResponse([0], sim.p.x[:1, :2], I2, np.zeros(2), splu(I2), -k * I2, stride=stride)


@pytest.mark.parametrize("stride", [2, 3, 5])
def test_a_strided_response_is_the_impulse_of_its_blocks(stride):
    """Stride s: nothing at s - 1 steps of each block of s, s times the force at its middle
    step; the force record back to 0 at the next skipped step; the fused loop the same bits
    as the Python loop; on a spring one block of s steps turns (x, v) by the angle of
    Verlet's method at the step s dt (to 1e-9; a period 0.4 / 1.1 / 4.5 % short of 2 pi /
    omega at s dt omega = 0.3 / 0.5 / 1), preserving area: stable, second order in s dt."""
    sim, resp = spring(stride=stride)
    applied = []
    for _ in range(3 * stride):
        sim.step(1, response=resp)
        applied.append(bool(resp.force.any()))
    expected = [(k - 1) % stride == (stride - 1) // 2 for k in range(1, 3 * stride + 1)]
    assert applied == expected and resp.count[0] == 3 * stride
    fused, loop = spring(stride=stride), spring(stride=stride)
    fused[0].step(40, response=fused[1])
    loop[0].step(40, hook=lambda: False, response=loop[1])
    assert np.array_equal(fused[0].p.x, loop[0].p.x) and np.array_equal(fused[0].p.v, loop[0].p.v)
    # one block's transfer matrix of (x, v) from two starts: its rotation angle is the
    # impulse method's, cos(omega' s dt) = 1 - (s dt omega)^2 / 2 (Verlet's at the block step)
    m, k = sim.p.mass[0], 5e4      # (a stiff spring: the steps below the contacts' limit)
    omega = np.sqrt(k / m)
    for sdw in (0.3, 0.5, 1.0):
        dt = sdw / (stride * omega)
        columns = []
        for x0, v0 in ((1e-6, 0.0), (0.0, 1e-6 * omega)):
            sim, resp = spring(k=k, stride=stride, dt=dt)
            sim.p.x[0, 0], sim.p.v[0, 0] = x0, v0
            sim.step(stride, response=resp)
            columns.append([sim.p.x[0, 0] / 1e-6, sim.p.v[0, 0] / (1e-6 * omega)])
        block = np.array(columns).T
        assert np.linalg.det(block) == pytest.approx(1.0, abs=1e-9)     # symplectic
        assert np.arccos(np.trace(block) / 2) == pytest.approx(np.arccos(1 - sdw**2 / 2), rel=1e-9)


def test_bad_shapes_are_refused():
    I2 = sp.identity(2, format="csc")
    with pytest.raises(ValueError, match="source must be"):
        LinearResponse([0, 1], np.zeros((2, 2)), I2, np.zeros(2), splu(I2), I2)
    with pytest.raises(ValueError, match="basis tables"):
        LinearResponse([0], np.zeros((1, 2)), I2, np.zeros(2), splu(I2), I2,
                       basis=(np.zeros((1, 2), int), np.ones((1, 3)), np.ones((1, 2))))
    with pytest.raises(ValueError, match="x_ref must be"):
        LinearResponse([0], np.zeros((2, 2)), I2, np.zeros(2), splu(I2), I2)
    with pytest.raises(ValueError, match="drift must be"):
        LinearResponse([0], np.zeros((1, 2)), I2, np.array([np.nan, 0.0]), splu(I2), I2)
    with pytest.raises(ValueError, match="stride must be"):
        LinearResponse([0], np.zeros((1, 2)), I2, np.zeros(2), splu(I2), I2, stride=0)


def test_ldl_factors_a_fixed_pattern_and_drives_the_response():
    """`dem.ldl.LDL`: A^-1 b to 1e-12 for SPD matrices of one pattern refactored with new
    values; an indefinite one and another pattern refused; the response through it equals
    the one through SuperLU's factors to 1e-12."""
    from dem.ldl import LDL
    rng = np.random.default_rng(4)
    n = 80
    B = sp.random(n, n, density=0.05, random_state=rng)
    pattern = ((B + B.T + sp.identity(n)) != 0).astype(float)

    def spd(seed):
        vals = sp.csr_matrix(pattern)
        vals.data = np.random.default_rng(seed).uniform(0.1, 1.0, vals.nnz)
        S = (vals + vals.T) / 2
        return (S + sp.diags(abs(S).sum(axis=1).A1 + 0.5)).tocsr()

    f = LDL(spd(0))
    for seed in (1, 2):
        A = spd(seed)
        b = rng.normal(size=n)
        f.factor(A)
        np.testing.assert_allclose(A @ f.solve(b), b, rtol=0, atol=1e-12 * abs(b).max())
    with pytest.raises(ValueError, match="not symmetric positive definite"):
        f.factor(A - 100 * sp.diags(np.ones(n)))
    with pytest.raises(ValueError, match="pattern"):
        f.factor(sp.identity(n))
    m = 10
    rows, x_ref = np.arange(m), np.zeros((m, 2))
    S = sp.random(n, 2 * m, density=0.3, random_state=rng)
    T = sp.random(2 * m, n, density=0.3, random_state=rng)
    A = spd(3)
    mat = dem.ContactMaterial(E=1e7, nu=0.25, density=2650.0, friction=0.3, restitution=0.5,
                              law="linear", kn=1e4, kt=5e3)
    apart = np.c_[np.arange(m) * 0.1, np.zeros(m)]       # (no contacts)
    sims = [dem.Simulation(dem.Particles.spheres(apart, 1e-3, 2650.0, dim=2), mat, dt=1e-5)
            for _ in range(2)]
    forces = []
    for sim, factors in zip(sims, (f.factor(A), splu(A.tocsc())), strict=True):
        resp = LinearResponse(rows, x_ref - 1e-3, S, np.ones(n) * 1e-4, factors, T)
        resp.apply(sim)
        forces.append(resp.force.copy())
    np.testing.assert_allclose(forces[0], forces[1], rtol=0, atol=1e-12 * abs(forces[1]).max())
    assert abs(forces[1]).max() > 0


def test_the_fused_loops_empty_response_has_the_responses_types():
    """`Simulation.step` hands the fused loop `dem.integrate._NO_RESPONSE` when there is no
    response: its types must be those of `LinearResponse.arrays` (through SuperLU's factors
    and `LDL`'s alike), or numba compiles the loop a second time for a saturated run."""
    from dem.integrate import _NO_RESPONSE
    from dem.ldl import LDL
    identity = sp.identity(4, format="csr")
    for factors in (splu(identity.tocsc()), LDL(identity)):
        arrays = LinearResponse([0, 1], np.zeros((2, 2)), identity, np.zeros(4), factors, identity).arrays()
        assert [(a.dtype, a.ndim) for a in arrays] == [(a.dtype, a.ndim) for a in _NO_RESPONSE]
