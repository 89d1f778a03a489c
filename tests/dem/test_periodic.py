"""Periodic cell with a velocity gradient: contacts through the faces equal the unwrapped
pair, a gas wrapping around conserves energy and momentum, and homogeneous simple shear of
a prestressed elastic lattice gives its analytic shear modulus."""

import numpy as np
import pytest

import dem
from dem.neighbours import build_periodic_pairs
from dem.periodic import PeriodicCell, cell_stress

R = 1.0e-3
RHO = 2650.0


def hertz(mu=0.5, e=0.5):
    return dem.ContactMaterial(E=2.9e8, nu=0.25, density=RHO, friction=mu, restitution=e)


@pytest.mark.parametrize("dim", [2, 3])
def test_pair_across_the_faces_equals_the_unwrapped_pair(dim):
    """i near x = 0 touches the image of j near x = Lx; with a shear rate the image moves
    at v_j + L h e_x. Forces and torques equal those of the unwrapped pair moving with the
    total velocities (fluctuation + L x)."""
    w = 8 * R
    h0 = np.diag([w, 1.1 * w, 0.9 * w][:dim])
    h0[0, 1] = 0.2 * w  # a tilted (sheared) cell
    lg = np.zeros((dim, dim))
    lg[0, 1], lg[1, 0] = 40.0, -15.0  # [1/s]
    cell = PeriodicCell(h0, lg)
    xi = np.array([0.4 * R, 0.5 * w, 0.4 * w])
    xj_image = xi + np.array([-1.9 * R, 0.3 * R, 0.2 * R])
    xj = xj_image + cell.h[:, 0]  # j sits at the far x face
    if dim == 2:
        xi[2] = xj[2] = xj_image[2] = 0.0
    rng = np.random.default_rng(1)
    v = rng.normal(0, 0.1, (2, 3))
    om = rng.normal(0, 50.0, (2, 3))
    if dim == 2:
        v[:, 2] = 0.0
        om[:, :2] = 0.0
    per = dem.Particles.spheres([xi, xj], R, RHO, dim=dim, v=v, omega=om)
    sim = dem.Simulation(per, hertz(), cell=cell, allow_overlap=True)
    assert len(sim.contacts()[0]) == 1
    vt = v + np.stack([xi, xj_image]) @ cell.velocity_gradient.T  # total velocities
    ref = dem.Particles.spheres([xi, xj_image], R, RHO, dim=dim, v=vt, omega=om)
    sim_ref = dem.Simulation(ref, hertz(), allow_overlap=True)
    assert np.abs(ref.force).max() > 0
    np.testing.assert_allclose(per.force, ref.force, rtol=0, atol=1e-12 * np.abs(ref.force).max())
    np.testing.assert_allclose(per.torque, ref.torque, rtol=0,
                               atol=1e-12 * np.abs(ref.torque).max())
    # and ten steps later, history included (the reference moves affinely by hand)
    for _ in range(10):
        sim.step(1)
        ref.v[:] = vt  # the reference integrates total velocities
        sim_ref.step(1)
        vt = ref.v.copy()
    d_per = sim._branches()[0]
    d_ref = ref.x[1] - ref.x[0]
    assert np.linalg.norm(d_per - d_ref) < 1e-3 * np.linalg.norm(d_ref)  # same geometry


def gas(dim, n, box, mu, e, lg=None, seed=0):
    """n particles on a jittered grid in a periodic box [m], speeds ~5 m/s."""
    rng = np.random.default_rng(seed)
    k = int(np.ceil(n ** (1 / dim)))
    g = np.stack(np.meshgrid(*[np.arange(k)] * dim, indexing="ij"), -1).reshape(-1, dim)[:n]
    x = (g + 0.5) * box / k + rng.uniform(-0.05, 0.05, g.shape) * box / k
    v = rng.normal(0, 5.0, (n, dim))
    v -= v.mean(axis=0)
    om = np.zeros((n, 3))
    om[:, 2 if dim == 2 else slice(None)] = rng.normal(0, 300.0, (n, 1 if dim == 2 else 3)) \
        if dim == 3 else rng.normal(0, 300.0, n)
    p = dem.Particles.spheres(x, R, RHO, dim=dim, v=v, omega=om)
    cell = PeriodicCell(np.eye(dim) * box, lg)
    return dem.Simulation(p, hertz(mu, e), cell=cell, safety=0.02), cell


@pytest.mark.parametrize("dim", [2, 3])
def test_dilute_gas_conserves_energy_and_momentum_across_wraps(dim):
    """Elastic frictionless disks/spheres in a fixed periodic box: particles wrap many
    times, collide through the faces, energy stays within the Hertz time error and the
    momentum is constant to round-off."""
    box = 7 * R
    sim, cell = gas(dim, 6 if dim == 2 else 8, box, 0.0, 1.0)
    p = sim.p
    mom0 = (p.mass[:, None] * p.v).sum(axis=0)
    travelled = np.zeros(p.n)
    collided = 0
    for _ in range(40):
        sim.step(100)
        travelled += 100 * sim.dt * np.linalg.norm(p.v, axis=1)
        collided = max(collided, len(sim.contacts()[0]))
    s = (p.x - cell.origin) @ np.linalg.inv(cell.h).T
    assert (s[:, :dim] > -0.2).all() and (s[:, :dim] < 1.2).all()  # kept in the cell
    assert travelled.max() > box  # wrapped around
    en = sim.energy()
    assert abs(en["balance"]) < 1e-4 * en["initial"]
    mom = (p.mass[:, None] * p.v).sum(axis=0)
    assert np.abs(mom - mom0).max() < 1e-12 * (p.mass * np.linalg.norm(p.v, axis=1)).sum()


def test_sheared_gas_conserves_fluctuation_momentum_and_keeps_history():
    """Friction, damping and a shear rate: the total fluctuation momentum stays constant
    (pair forces cancel, also through the faces), the ledger of a cell at rest closes."""
    lg = np.array([[0.0, 300.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    sim, cell = gas(3, 8, 7 * R, 0.5, 0.5, lg=lg, seed=2)
    p = sim.p
    mom0 = (p.mass[:, None] * p.v).sum(axis=0)
    sticking = 0
    for _ in range(30):
        sim.step(100)
        sticking = max(sticking, int((sim.nl.etan > 0).sum()))
    assert sticking > 0 and cell.deformation_gradient[0, 1] > 0.2
    mom = (p.mass[:, None] * p.v).sum(axis=0)
    assert np.abs(mom - mom0).max() < 1e-12 * (p.mass * np.linalg.norm(p.v, axis=1)).sum()


def triangular_lattice(nx, ny, a):
    j, i = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    x = np.column_stack([((i + 0.5 * (j % 2)) * a).ravel(),
                         (j * a * np.sqrt(3) / 2).ravel()])
    return x + 0.25 * a, np.diag([nx * a, ny * a * np.sqrt(3) / 2])


def fcc_lattice(n, ac):
    base = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]])
    g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 1, 3)
    return ((g + base).reshape(-1, 3) + 0.25) * ac, np.eye(3) * n * ac


def affine_bond_stress(x, h0, r, kn, gamma, dim):
    """Independent route: 1/V sum over bonds of -kn (2r - |F d|) (F d) (x) (F d) / |F d|,
    bonds = nearest-image neighbours closer than 2r of the undeformed lattice."""
    hinv = np.linalg.inv(h0)
    d = x[None, :, :] - x[:, None, :]
    s = d @ hinv.T
    d = (s - np.round(s)) @ h0.T
    dist = np.linalg.norm(d, axis=2)
    i, j = np.nonzero(np.triu((dist < 2 * r) & (dist > 0), 1))
    F = np.eye(dim)
    F[0, 1] = gamma
    b = d[i, j] @ F.T
    lb = np.linalg.norm(b, axis=1)
    f = -kn * (2 * r - lb)[:, None] * b / lb[:, None]  # force on i by j (push apart)
    return np.einsum("ck,cl->kl", b, f) / np.linalg.det(h0)


@pytest.mark.parametrize("dim", [2, 3])
def test_simple_shear_of_a_lattice_gives_its_shear_modulus(dim):
    """A prestressed (overlap eps = 1e-3 of the spacing) elastic lattice with linear
    frictionless contacts under L = gamma_dot e_x (x) e_y deforms affinely (every particle
    is a centre of symmetry): the cell stress equals the bond sum of the affinely deformed
    lattice to 1e-9, and, in 2D, the closed form of the triangular lattice,
    sigma_xy = sqrt(3)/4 kn (1 - 3 eps) gamma (prestress included; `dem.bonded`'s
    sqrt(3)/4 (kn + kt) without it)."""
    kn, eps = 2e4, 1e-3
    if dim == 2:
        a = 2 * R
        x, h0 = triangular_lattice(6, 6, a)
    else:
        a = 2 * R  # bond length of the fcc lattice
        x, h0 = fcc_lattice(2, a * np.sqrt(2))
    r = 0.5 * a * (1 + eps)
    mat = dem.ContactMaterial(E=1e8, nu=0.25, density=RHO, friction=0.0, restitution=1.0,
                              law="linear", kn=kn, kt=1e4)
    p = dem.Particles.spheres(x, r, RHO, dim=dim)
    sim = dem.Simulation(p, mat, cell=PeriodicCell(h0), allow_overlap=True)
    nsteps = 200
    rate = 1e-4 / (nsteps * sim.dt)  # [1/s]: a shear strain of 1e-4 in 200 steps
    sim.cell.velocity_gradient[0, 1] = rate
    sim.step(nsteps)
    gamma = nsteps * sim.dt * rate  # (I + dt L)^n = I + n dt L: L is nilpotent
    assert sim.cell.deformation_gradient[0, 1] == pytest.approx(gamma, rel=1e-12)
    assert len(sim.contacts()[0]) == len(x) * (3 if dim == 2 else 6)
    sig = cell_stress(sim)
    ref = np.zeros((3, 3))
    ref[:dim, :dim] = affine_bond_stress(x, h0[:dim, :dim], r, kn, gamma, dim)
    assert np.abs(sig - ref).max() < 1e-9 * np.abs(ref).max()
    assert abs(sig[0, 1]) > 1e-3 * abs(sig[0, 0])  # a shear response, not round-off
    assert np.abs(p.v).max() * sim.dt < 1e-12 * a  # no fluctuations: affine
    if dim == 2:
        mu = np.sqrt(3) / 4 * kn * (1 - 3 * eps)
        assert sig[0, 1] == pytest.approx(mu * gamma, rel=2e-3)


def test_periodic_pairs_equal_brute_force_images():
    """Cell-list search in a sheared periodic cell against all 27 images by brute force."""
    rng = np.random.default_rng(5)
    n = 300
    h = np.array([[0.02, 0.006, 0.0], [0.0, 0.018, 0.002], [0.0, 0.0, 0.021]])
    x = rng.uniform(0, 1, (n, 3)) @ h.T
    r = rng.uniform(0.5e-3, 1.2e-3, n)
    skin = 2e-4
    pi, pj, img = build_periodic_pairs(x, r, skin, h)
    got = {(int(a), int(b)) for a, b in zip(pi, pj, strict=False)}
    want = set()
    shifts = np.stack(np.meshgrid(*[[-1, 0, 1]] * 3, indexing="ij"), -1).reshape(-1, 3)
    for i in range(n):
        d = x[i + 1:, None, :] + shifts @ h.T - x[i]
        close = (np.linalg.norm(d, axis=2) < (r[i] + r[i + 1:] + skin)[:, None]).any(axis=1)
        want |= {(i, i + 1 + k) for k in np.flatnonzero(close)}
    assert got == want and len(got) > 100
    b = x[pj] - x[pi] + img @ h.T
    assert (np.linalg.norm(b, axis=1) < r[pi] + r[pj] + skin).all()


def sheared_packing(mu, e, law="linear", jitter=0.0, seed=0, safety=None):
    """A prestressed triangular lattice of 2D disks (6 x 6, overlaps 1e-3 of the spacing),
    positions jittered by ``jitter`` x the spacing; linear or Hertz contacts."""
    a, eps = 2 * R, 1e-3
    x, h0 = triangular_lattice(6, 6, a)
    x = x + np.random.default_rng(seed).uniform(-jitter, jitter, x.shape) * a
    kw = dict(kn=2e4, kt=1.6e4) if law == "linear" else {}
    mat = dem.ContactMaterial(E=1e8, nu=0.25, density=RHO, friction=mu, restitution=e,
                              law=law, **kw)
    p = dem.Particles.spheres(x, 0.5 * a * (1 + eps), RHO, dim=2)
    return dem.Simulation(p, mat, cell=PeriodicCell(h0), allow_overlap=True, safety=safety)


def scale(en):
    return en["initial"] + abs(en["work_cell"])


def test_cell_work_is_the_stored_energy_of_an_affine_shear():
    """The elastic lattice sheared affinely (no fluctuations, nothing dissipated): the work
    of the cell, V sigma : L dt a step, is the change of the elastic energy, so the ledger
    closes (to the second-order error of taking each step's stress at its two ends)."""
    sim = sheared_packing(0.0, 1.0)
    sim.cell.velocity_gradient[0, 1] = 1e-2 / (400 * sim.dt)  # a strain of 1 % in 400 steps
    e0 = sim.energy()["elastic"]
    sim.step(400)
    en = sim.energy()
    assert en["work_cell"] > 0.5 * e0  # a real energy input, not round-off
    assert en["work_cell"] == pytest.approx(en["elastic"] - e0, rel=1e-6)
    assert abs(en["balance"]) < 1e-6 * scale(en)


def shear_residual(law, refine):
    """A disordered packing (jittered lattice) relaxes, then is sheared to 5 % with damping
    and sliding friction, at the law's default time step over ``refine``: the largest
    change of the balance during the shear over the cell's work (the relaxation's own time
    error, at contacts opening, taken out), and the final ledger with the one before the
    shear."""
    from dem.timestep import DEFAULT_SAFETY

    sim = sheared_packing(0.3, 0.5, law, jitter=0.002, seed=3,
                          safety=DEFAULT_SAFETY[law] / refine)
    sim.step(300 * refine)
    en0 = sim.energy()
    n = 2000 * refine
    sim.cell.velocity_gradient[0, 1] = 5e-2 / (n * sim.dt)
    worst = 0.0
    for _ in range(20):
        sim.step(n // 20)
        en = sim.energy()
        worst = max(worst, abs(en["balance"] - en0["balance"]))
    return worst / en["work_cell"], en, en0


@pytest.mark.parametrize("law, tol", [("linear", 1e-5), ("hertz_mindlin", 1e-7)])
def test_ledger_closes_under_shear(law, tol):
    """With the cell's work booked the ledger stays closed under shear: the work goes into
    elastic energy, damping and friction, and what is left is a second-order time error
    (measured at the default step and half of it: 6.8e-6 and 1.8e-6 of the work for linear
    contacts, 3.3e-8 and 8.2e-9 for Hertz; from contacts opening and closing, where the
    normal force is not smooth)."""
    res, en, en0 = shear_residual(law, 1)
    assert en["work_cell"] > 10 * en["initial"] and en["elastic"] > 10 * en0["elastic"]
    assert en["dissipated_damping"] > 1.5 * en0["dissipated_damping"]
    assert en["dissipated_friction"] > 2 * en0["dissipated_friction"] > 0
    assert res < tol
    assert shear_residual(law, 2)[0] < res / 3  # second order in dt
