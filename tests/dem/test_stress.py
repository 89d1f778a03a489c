"""Micromorphic stress measures (seed 002 eq. 1-15) on linear-spring fcc lattices.

The lattice stays at its reference geometry and carries the small-strain affine contact
forces of a bonded linear spring network, f = k_n d (n.eps.n) n + k_t d (eps n - (n.eps.n) n)
(force on i by j, n from i to j, d the bond length). For uniform eps every particle is in
force and moment equilibrium (bond pairs +-n cancel, cubic symmetry kills the torques),
and the expected stresses follow from the 6 bond directions of the cubic cell alone.
RVE faces are offset by A/8 from the lattice so each RVE holds whole cells of contacts.
"""

import itertools

import numpy as np
import pytest
from scipy.spatial import cKDTree

from dem.stress import (
    AveragingDomain,
    EmptyRVEError,
    contact_points,
    couple_measures,
    love_weber_stress,
    mean_stress,
    micromorphic_stress,
    octahedral_shear,
)

A = 2e-3                      # fcc cell edge [m]
D = A / np.sqrt(2)            # bond length = 2 r [m]
KN, KT = 2e6, 0.7e6           # normal / tangential spring stiffness [N/m]
EPS0 = -1e-3 * np.array([[1.0, 0.3, -0.2], [0.3, 0.6, 0.25], [-0.2, 0.25, 1.4]])
DIRS = np.array([[1, 1, 0], [1, -1, 0], [1, 0, 1], [1, 0, -1], [0, 1, 1], [0, 1, -1]]) / np.sqrt(2)


def _fcc(ncell):
    cells = np.array(list(itertools.product(range(ncell), repeat=3)), float)
    sites = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]])
    x = ((cells[:, None, :] + sites[None]) * A).reshape(-1, 3)
    pairs = cKDTree(x).query_pairs(1.001 * D, output_type="ndarray")
    return x, np.full(len(x), D / 2), pairs


def _bond_force(n, eps, w=None):
    """Force on i by j for bond direction(s) n (c, 3) under strain(s) eps (c, 3, 3)."""
    en = np.einsum("...kl,...l->...k", eps, n)
    nen = np.einsum("...k,...k->...", n, en)[..., None]
    f = KN * D * nen * n + KT * D * (en - nen * n)
    if w is not None:
        f = f + KT * D * np.einsum("kl,...l->...k", w, n)
    return f


def _forces(x, pairs, eps_of_x, w=None):
    n = (x[pairs[:, 1]] - x[pairs[:, 0]]) / D
    xc = 0.5 * (x[pairs[:, 0]] + x[pairs[:, 1]])
    return _bond_force(n, eps_of_x(xc), w)


def _cell_stress(eps, symmetric=True):
    """Stress of the uniform lattice from the cubic cell: 4 bonds per direction per A^3."""
    t = 4 * D / A**3 * sum(np.outer(n, _bond_force(n, eps)) for n in DIRS)  # b_k f_l
    return 0.5 * (t + t.T) if symmetric else t


def _domain(ncell_per_rve, divisions):
    lo = np.full(3, A + A / 8)
    return AveragingDomain(tuple(lo), tuple(lo + A * ncell_per_rve * np.array(divisions)),
                           divisions)


@pytest.fixture(scope="module")
def lattice():
    return _fcc(7)


@pytest.mark.parametrize("divisions", [(1, 1, 1), (2, 2, 2), (4, 2, 1)])
def test_homogeneous_state(lattice, divisions):
    x, r, pairs = lattice
    f = _forces(x, pairs, lambda p: np.broadcast_to(EPS0, (len(p), 3, 3)))
    dom = _domain(4 // max(divisions), divisions)
    res = micromorphic_stress(dom, x, r, pairs, f, couple_flux="none")
    expect = _cell_stress(EPS0)
    scale = np.abs(expect).max()
    assert np.all(res.rve_contacts > 0)
    assert np.abs(res.rve_stress - expect).max() < 1e-13 * scale
    assert np.abs(res.s - expect).max() < 1e-13 * scale
    assert np.abs(res.sigma - res.s).max() == 0.0  # no flux, gravity or acceleration
    L = max(np.subtract(dom.hi, dom.lo))
    assert np.abs(res.m).max() < 1e-13 * scale * L
    # equilibrium: the unsymmetric granular stress is symmetric and equals s
    assert np.abs(res.sigma_G - _cell_stress(EPS0, symmetric=False)).max() < 1e-13 * scale
    assert np.abs(res.sigma_G - res.sigma_G.T).max() < 1e-13 * scale
    assert np.abs(res.sigma_G - res.s).max() < 1e-13 * scale
    # eq. 12 as written: for a homogeneous state sigma_mk = s_mk / n_m (module caveat)
    faces = micromorphic_stress(dom, x, r, pairs, f, couple_flux="faces")
    n_m = np.array(divisions, float)[:, None]
    assert np.abs(faces.sigma - res.s / n_m).max() < 1e-13 * scale
    assert res.measures()["p_s"] == pytest.approx(np.trace(expect) / 3, rel=1e-13)


def test_love_weber_matches_domain_and_contact_points(lattice):
    x, r, pairs = lattice
    f = _forces(x, pairs, lambda p: np.broadcast_to(EPS0, (len(p), 3, 3)))
    xc = contact_points(x, r, pairs)
    np.testing.assert_allclose(xc, 0.5 * (x[pairs[:, 0]] + x[pairs[:, 1]]), atol=1e-15)
    dom = _domain(2, (2, 2, 2))
    mask = dom.locate(xc) >= 0
    lw = love_weber_stress(x, pairs, f, dom.volume, mask)
    res = micromorphic_stress(dom, x, r, pairs, f)
    assert np.abs(lw - res.s).max() < 1e-13 * np.abs(lw).max()


def test_granular_stress_unsymmetric_out_of_moment_equilibrium(lattice):
    """Tangential forces of a rotation mismatch w (particles not rotating with the
    lattice) leave torques on the particles; sigma^G then has the antisymmetric part
    4 d^2 k_t / A^3 sum_n n (w n), and s, its symmetric part, is unchanged."""
    x, r, pairs = lattice
    w = 1e-3 * np.array([[0, -0.5, 0.2], [0.5, 0, -0.8], [-0.2, 0.8, 0]])
    f = _forces(x, pairs, lambda p: np.broadcast_to(EPS0, (len(p), 3, 3)), w)
    dom = _domain(2, (2, 2, 2))
    res = micromorphic_stress(dom, x, r, pairs, f)
    expect_skew = 4 * D**2 * KT / A**3 * sum(np.outer(n, w @ n) for n in DIRS)
    skew = 0.5 * (res.sigma_G - res.sigma_G.T)
    assert np.abs(skew - expect_skew).max() < 1e-12 * np.abs(expect_skew).max()
    assert np.abs(expect_skew).max() > 0.1 * np.abs(res.s).max()
    assert np.abs(res.s - _cell_stress(EPS0)).max() < 1e-13 * np.abs(res.s).max()


def test_linear_gradient_couple_stress_and_split_independence(lattice):
    """eps(x) = eps0 + G_p (x - c)_p: each RVE stress is linear in its centre, so eq. 6 gives
    m_klm = Gamma_klp J_pm with Gamma_klp = d sigma_kl / d x_p (cell formula) and
    J_pm = delta_pm L^2 (n^2 - 1) / (12 n^2) the second moment of the RVE centres."""
    x, r, pairs = lattice
    rng = np.random.default_rng(1)
    G = 1e-2 * rng.normal(size=(3, 3, 3))
    G = 0.5 * (G + G.transpose(1, 0, 2))       # G[k, l, p] = d eps_kl / d x_p [1/m]
    Gamma = np.stack([_cell_stress(G[:, :, p]) for p in range(3)], axis=-1)
    L = 4 * A
    out = {}
    for nd in (1, 2, 4):
        dom = _domain(4 // nd, (nd,) * 3)
        c = dom.centre
        f = _forces(x, pairs, lambda p, c=c: EPS0 + np.einsum("klp,cp->ckl", G, p - c))
        out[nd] = res = micromorphic_stress(dom, x, r, pairs, f)
        J = np.eye(3) * L**2 * (nd**2 - 1) / (12 * nd**2)
        expect_m = np.einsum("klp,pm->klm", Gamma, J)
        scale = np.abs(Gamma).max() * L**2
        assert np.abs(res.m - expect_m).max() < 1e-12 * scale
        if nd > 1:
            assert np.abs(expect_m).max() > 1e-3 * scale
    ref = out[1]
    for nd in (2, 4):  # volume averages over the same contacts do not depend on the split
        for name in ("s", "sigma_G"):  # not sigma: the face flux depends on the split
            a, b = getattr(out[nd], name), getattr(ref, name)
            assert np.abs(a - b).max() < 1e-13 * np.abs(b).max()
    p_c, tau_c = couple_measures(out[4].m)
    assert p_c > 0 and tau_c > 0
    assert out[4].measures()["tau_couple_per_xi"] == pytest.approx(tau_c / out[4].xi_length)


def test_inertia_and_body_couple(lattice):
    x, r, pairs = lattice
    f = _forces(x, pairs, lambda p: np.broadcast_to(EPS0, (len(p), 3, 3)))
    dom = _domain(2, (2, 2, 2))
    mass = np.full(len(x), 1e-5)
    g = np.array([0.0, 0.0, -9.81])
    # uniform density, symmetric RVEs: no body couple; uniform acceleration: no spin inertia
    res = micromorphic_stress(dom, x, r, pairs, f, mass, accel=np.tile([1.0, -2.0, 3.0],
                                                                       (len(x), 1)), gravity=g)
    assert np.abs(res.body_couple).max() < 1e-12 * np.abs(res.s).max()
    assert np.abs(res.spin_inertia).max() < 1e-12 * np.abs(res.s).max()
    # heavier particles on top: body couple 1/V sum_R M_R g_k xi_m, only the (z, z) entry
    heavy = mass * (1 + (x[:, 2] > dom.centre[2]))
    res = micromorphic_stress(dom, x, r, pairs, f, heavy, gravity=g)
    upper = res.xi[:, 2] > 0
    expect = (res.rve_mass[upper].sum() - res.rve_mass[~upper].sum()) * g[2] * A / dom.volume
    assert res.body_couple[2, 2] == pytest.approx(expect, rel=1e-12)
    assert np.abs(res.body_couple).sum() == pytest.approx(abs(expect), rel=1e-12)
    np.testing.assert_allclose(res.sigma_no_spin, res.s - res.couple_flux - res.body_couple)
    # a spin field a = W xi (rotation acceleration) gives spin inertia 1/V sum M_R (W xi_R) xi_R
    W = np.array([[0, -5.0, 0], [5.0, 0, 0], [0, 0, 0]])
    acc = (x - dom.centre) @ W.T
    res = micromorphic_stress(dom, x, r, pairs, f, mass, accel=acc)
    owner = dom.locate(x)
    expect = np.zeros((3, 3))
    for R in range(dom.n_rve):
        sel = owner == R
        expect += np.outer(res.xi[R], (mass[sel, None] * acc[sel]).sum(0))
    expect /= dom.volume
    assert np.abs(res.spin_inertia - expect).max() < 1e-12 * np.abs(expect).max()


def test_measures():
    t = np.diag([-3.0, -2.0, -1.0])
    assert mean_stress(t) == -2.0
    assert octahedral_shear(t) == pytest.approx(np.sqrt(((1) ** 2 + 1 + 4) / 9))
    assert octahedral_shear(np.eye(3) * 5) == 0.0
    m = np.zeros((3, 3, 3))
    m[0, 0, 2] = m[1, 1, 2] = m[2, 2, 2] = 3.0   # pure "mean" couple along z
    assert couple_measures(m) == pytest.approx((3.0, 0.0))


def test_bad_input(lattice):
    x, r, pairs = lattice
    f = _forces(x, pairs, lambda p: np.broadcast_to(EPS0, (len(p), 3, 3)))
    with pytest.raises(ValueError, match="zero volume"):
        AveragingDomain((0, 0, 0), (1, 0, 1))
    with pytest.raises(ValueError, match="divisions"):
        AveragingDomain((0, 0, 0), (1, 1, 1), (2, 0, 1))
    with pytest.raises(ValueError, match="holds no particle centre"):
        micromorphic_stress(AveragingDomain((1, 1, 1), (2, 2, 2)), x, r, pairs, f)
    # a domain reaching past the lattice: RVEs out there have no contact
    big = AveragingDomain((A, A, A), (A + 12 * A, 2 * A, 2 * A), (6, 1, 1))
    with pytest.raises(EmptyRVEError, match="RVEs hold no contact point"):
        micromorphic_stress(big, x, r, pairs, f)
    res = micromorphic_stress(big, x, r, pairs, f, on_empty="zero")
    assert np.all(np.isfinite(res.sigma)) and res.measures()["empty_rves"] > 0
    with pytest.raises(ValueError, match="force must have shape"):
        micromorphic_stress(big, x, r, pairs, f[:-1])
    with pytest.raises(ValueError, match="couple_flux"):
        micromorphic_stress(big, x, r, pairs, f, couple_flux="x")
    with pytest.raises(ValueError, match="mass"):
        micromorphic_stress(_domain(2, (1, 1, 1)), x, r, pairs, f, gravity=(0, 0, -9.81))
    with pytest.raises(ValueError, match="volume must be > 0"):
        love_weber_stress(x, pairs, f, 0.0)


def test_recorder_series(lattice, tmp_path):
    import csv
    import json

    from dem.stress import StressRecorder

    x, r, pairs = lattice
    dom = _domain(2, (2, 2, 2))
    mass = np.full(len(x), 1e-5)
    W = np.array([[0, -5.0, 0], [5.0, 0, 0], [0, 0, 0]])
    rec = StressRecorder(dom, tmp_path, every=2, gravity=(0, 0, -9.81))
    for step in range(7):
        t = step * 1e-3
        load = 1 + step / 6
        f = _forces(x, pairs, lambda p, load=load: np.broadcast_to(load * EPS0, (len(p), 3, 3)))
        v = t * (x - dom.centre) @ W.T   # angular acceleration W, so (v - v_prev)/dt = W xi
        rec(step, t, x, r, pairs, f, mass, v=v)
    paths = rec.write()
    rows = list(csv.DictReader(open(paths["csv"])))
    assert [int(row["step"]) for row in rows] == [0, 2, 4, 6]
    p = [float(row["p_s"]) for row in rows]
    np.testing.assert_allclose(p, [np.trace(_cell_stress(EPS0)) / 3 * (1 + s / 6)
                                   for s in (0, 2, 4, 6)], rtol=1e-12)
    assert [row["has_accel"] for row in rows] == ["False", "True", "True", "True"]
    data = json.load(open(paths["json"]))
    assert len(data["tensors"]) == 4 and np.array(data["tensors"][0]["m"]).shape == (3, 3, 3)
    # spin inertia of the finite-difference acceleration equals that of accel = W xi
    direct = micromorphic_stress(dom, x, r, pairs, f, mass, accel=(x - dom.centre) @ W.T,
                                 gravity=(0, 0, -9.81))
    assert np.abs(direct.spin_inertia).max() > 1e-9 * np.abs(direct.s).max()
    np.testing.assert_allclose(data["tensors"][-1]["sigma"], direct.sigma, rtol=1e-12)
    no_acc = micromorphic_stress(dom, x, r, pairs, f, mass, gravity=(0, 0, -9.81))
    assert np.abs(no_acc.sigma - direct.sigma).max() > 0
    import matplotlib.image
    img = matplotlib.image.imread(paths["png"])
    assert img.std() > 0.05
    with pytest.raises(ValueError, match="every"):
        StressRecorder(dom, tmp_path, every=0)


def test_two_dimensional_square_lattice():
    """Disks of unit thickness: volumes are areas; bonds (1, 0), (0, 1) per cell a^2."""
    a = 1e-3
    g = np.arange(12) * a
    x = np.zeros((144, 3))
    x[:, :2] = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    pairs = cKDTree(x).query_pairs(1.001 * a, output_type="ndarray")
    eps = -1e-3 * np.array([[1.0, 0.4, 0], [0.4, 0.5, 0], [0, 0, 0]])
    n = (x[pairs[:, 1]] - x[pairs[:, 0]]) / a
    en = n @ eps.T
    nen = np.sum(n * en, axis=1)[:, None]
    f = KN * a * nen * n + KT * a * (en - nen * n)
    dom = AveragingDomain((2.25 * a, 3.25 * a), (10.25 * a, 9.25 * a), (4, 3))
    res = micromorphic_stress(dom, x, np.full(144, a / 2), pairs, f)
    expect = np.zeros((3, 3))
    for e in np.eye(3)[:2]:
        fe = KN * a * (e @ eps @ e) * e + KT * a * (eps @ e - (e @ eps @ e) * e)
        expect += a / a**2 * 0.5 * (np.outer(fe, e) + np.outer(e, fe))
    assert dom.volume == pytest.approx(8 * 6 * a**2)
    assert np.abs(res.rve_stress - expect).max() < 1e-13 * np.abs(expect).max()
    assert np.abs(res.sigma_G - expect).max() < 1e-13 * np.abs(expect).max()
    assert np.all(res.xi[:, 2] == 0) and np.all(res.m[:, :, 2] == 0)


def test_stress_from_saved_frames_equals_live(tmp_path):
    """The measures computed on saved contact frames equal those recorded during the run."""
    from dem import ContactMaterial, Particles, Simulation, box_walls
    from dem.io import write_contact_frame
    from dem.packing import lattice_packing
    from dem.stress import AveragingDomain, StressRecorder, record_frames

    x, r = lattice_packing((0, 0, 0), (0.012, 0.012, 0.012), 1e-3, kind="sc", gap=0.0)
    p = Particles.spheres(x, r * 1.001, 2650.0)  # slight overlaps: contacts from the start
    mat = ContactMaterial(E=1e7, nu=0.25, density=2650.0, friction=0.5, restitution=0.5)
    sim = Simulation(p, mat, walls=box_walls((0, 0, 0), (0.012, 0.012, 0.012), top=True),
                     gravity=(0, 0, -9.81), allow_overlap=True)
    domain = AveragingDomain((0.002, 0.002, 0.002), (0.010, 0.010, 0.010), (2, 2, 2))
    live = StressRecorder(domain, tmp_path / "live")
    paths = []
    for k in range(3):
        sim.step(20)
        pairs, force = sim.contact_forces()
        live(sim.nsteps, sim.time, p.x, p.radius, pairs, force, p.mass, v=p.v)
        paths.append(write_contact_frame(tmp_path / f"frame{k}.npz", sim))
    saved = StressRecorder(domain, tmp_path / "saved")
    record_frames(saved, paths)
    assert len(saved.rows) == len(live.rows) == 3
    for a, b in zip(live.rows, saved.rows, strict=False):
        for key in a:
            assert np.allclose(a[key], b[key], rtol=1e-12, atol=0), key
