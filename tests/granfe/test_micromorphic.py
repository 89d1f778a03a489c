"""Small-strain micromorphic elasticity: the material-point law against an independent
tensor evaluation, Smith's admissibility conditions against eigenvalues, UFL = numpy, the
patch test, manufactured-solution rates, the micropolar limit, serial = 2 ranks."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
import ufl
from dolfinx import fem, mesh
from micromorphic_reference import tensors

from granfe.materials import MicropolarMaterial
from granfe.models.micromorphic import (
    Micromorphic,
    MicromorphicMaterial,
    micromorphic_energy,
    micromorphic_stresses,
    stresses,
)
from granfe.problem import ContinuumProblem, MicropolarProblem

NAMES = ("lam", "mu", "eta", "tau", "kappa", "nu", "sigma") + tuple(f"tau{i}" for i in range(1, 12))
MAT = MicromorphicMaterial(lam=2.0, mu=1.0, eta=0.5, tau=0.2, kappa=1.5, nu=0.3, sigma=0.1,
                           tau1=0.1, tau2=0.05, tau3=0.2, tau4=0.15, tau5=0.05, tau6=0.1,
                           tau7=1.0, tau8=0.2, tau9=0.1, tau10=0.15, tau11=0.05)


def everywhere(x):
    return np.full(x.shape[1], True)


def fix_zero(problem, where, field):
    """Clamp every component of a field: a number broadcasts over vector and tensor fields."""
    bcs = problem.fix(where, field, 0.0)
    f = problem.fields[[g.name for g in problem.fields].index(field)]
    if f.shape:
        assert len(bcs) == len(f.components)


def _energy(grad_u, phi, G, p):
    d = len(grad_u)
    A, B, C, D = tensors(p, d)
    eps, E = (grad_u + grad_u.T) / 2, grad_u.T + phi
    return (np.einsum("ij,ijkl,kl", eps, A, eps) / 2 + np.einsum("ij,ijkl,kl", E, B, E) / 2
            + np.einsum("ijk,ijkpqr,pqr", G, C, G) / 2 + np.einsum("ij,ijkl,kl", eps, D, E))


def _central_difference(f, X, h=1e-6):
    out = np.zeros_like(X)
    for idx in np.ndindex(X.shape):
        Xp, Xm = X.copy(), X.copy()
        Xp[idx] += h
        Xm[idx] -= h
        out[idx] = (f(Xp) - f(Xm)) / (2 * h)
    return out


def test_tensors_match_tardigrade():
    """The delta-built tensors of the independent route reproduce the leading entries of
    Tardigrade's own unit-test answers (test_tardigrade_hydraMicromorphicLinearElasticity.cpp,
    ``testFormIsotropicA..D``; row-major, 3D)."""
    p = dict(lam=4.0, mu=7.0, eta=3.0, tau=5.0, kappa=6.0, nu=8.0, sigma=4.0,
             **{f"tau{i}": float(i + 1) for i in range(1, 12)})
    A, B, C, D = tensors(p, 3)
    assert A.reshape(-1)[:13].tolist() == [18, 0, 0, 0, 4, 0, 0, 0, 4, 0, 7, 0, 7]
    assert B.reshape(-1)[:13].tolist() == [4, 0, 0, 0, -2, 0, 0, 0, -2, 0, 2, 0, 4]
    assert D.reshape(-1)[:13].tolist() == [13, 0, 0, 0, 5, 0, 0, 0, 5, 0, 4, 0, 4]
    assert C.reshape(-1)[:39].tolist() == [97, 0, 0, 0, 13, 0, 0, 0, 13, 0, 16, 0, 9,
                                           0, 0, 0, 0, 0, 0, 0, 16, 0, 0, 0, 9, 0,
                                           0, 0, 23, 0, 22, 0, 0, 0, 0, 0, 23, 0, 0]
    assert C.reshape(-1)[-1] == 97


@pytest.mark.parametrize("d", [2, 3])
def test_stresses_are_energy_derivatives(d):
    """sigma = dW/d grad u, s - sigma = dW/d phi, m = dW/d grad phi of the energy built from
    the full isotropic tensors (W quadratic: central differences exact to round-off), for an
    indefinite random modulus set (every term enters)."""
    rng = np.random.default_rng(7 + d)
    p = dict(zip(NAMES, rng.normal(size=18), strict=True))
    mat = MicromorphicMaterial(**p, allow_indefinite=True)
    grad_u, phi, G = rng.normal(size=(d, d)), rng.normal(size=(d, d)), rng.normal(size=(d, d, d))
    chi = np.eye(d) + phi
    sigma, s, m = micromorphic_stresses(grad_u, chi, G, mat)
    assert micromorphic_energy(grad_u, chi, G, mat) == pytest.approx(_energy(grad_u, phi, G, p),
                                                                     rel=1e-13)
    tol = 1e-7 * (1 + np.abs(sigma).max() + np.abs(m).max())
    assert np.abs(_central_difference(lambda X: _energy(X, phi, G, p), grad_u) - sigma).max() < tol
    assert np.abs(_central_difference(lambda X: _energy(grad_u, X, G, p), phi) - (s - sigma)).max() < tol
    assert np.abs(_central_difference(lambda X: _energy(grad_u, phi, X, p), G) - m).max() < tol
    assert np.array_equal(s, np.swapaxes(s, -1, -2))
    # batches broadcast over leading axes
    sb, _, mb = micromorphic_stresses(np.stack([grad_u] * 3), np.stack([chi] * 3),
                                      np.stack([G] * 3), mat)
    assert np.allclose(sb[1], sigma, rtol=1e-15, atol=0) and np.allclose(mb[2], m, rtol=1e-15, atol=0)


def _sym_basis():
    out = []
    for i in range(3):
        for j in range(i, 3):
            M = np.zeros((3, 3))
            M[i, j] = M[j, i] = 1.0
            out.append(M / np.linalg.norm(M))
    return np.array(out)


def test_smith_conditions_equal_positive_definiteness():
    """Over random moduli, the (eps, E) conditions hold iff the 15x15 form of A, B, D is
    positive definite, and the grad-chi ones iff the 27x27 matrix of C is."""
    rng = np.random.default_rng(1)
    S, Eb = _sym_basis(), np.eye(9).reshape(9, 3, 3)
    shift = np.zeros(18)
    shift[[1, 2, 4, 13]] = (1.0, 0.5, 2.0, 2.0)   # mu, eta, kappa, tau7: both outcomes occur
    seen = np.zeros((2, 2), dtype=int)
    for _ in range(600):
        p = dict(zip(NAMES, rng.normal(size=18) + shift, strict=True))
        A, B, C, D = tensors(p, 3)
        K = np.zeros((15, 15))
        K[:6, :6] = np.einsum("aij,ijkl,bkl->ab", S, A, S)
        K[6:, 6:] = np.einsum("aij,ijkl,bkl->ab", Eb, B, Eb)
        K[:6, 6:] = np.einsum("aij,ijkl,bkl->ab", S, D, Eb)
        K[6:, :6] = K[:6, 6:].T
        values = [v for _, v in MicromorphicMaterial(**p, allow_indefinite=True).conditions()]
        pd_abd, pd_c = np.linalg.eigvalsh(K).min() > 0, np.linalg.eigvalsh(C.reshape(27, 27)).min() > 0
        assert (min(values[:7]) > 0) == pd_abd
        assert (min(values[7:]) > 0) == pd_c
        seen[int(pd_abd), int(pd_c)] += 1
    assert seen[:, 1].sum() > 10 and seen[1, :].sum() > 10 and seen[0, :].sum() > 10


@pytest.mark.parametrize("change, rule", [
    (dict(mu=-0.1), r"mu > 0"),
    (dict(kappa=0.2), r"kappa - nu > 0"),
    (dict(sigma=0.6), r"mu \(kappa \+ nu - 2 sigma\) - 2 sigma\^2 > 0"),
    (dict(lam=-1.0), r"3 lam \+ 2 mu > 0"),
    (dict(eta=-1.0), r"kappa \+ nu \+ 3 eta - 3 tau - 2 sigma > 0"),
    (dict(tau=1.0), r"\(3 tau \+ 2 sigma\)\^2 > 0"),
    (dict(tau8=0.95), r"mixed-symmetry part"),
    (dict(tau9=0.9, tau10=0.9), r"totally skew part"),
    (dict(tau3=-3.0), r"Smith's T"),
])
def test_inadmissible_moduli_are_named(change, rule):
    kwargs = {**MAT.moduli(), **change}
    with pytest.raises(ValueError, match=rule):
        MicromorphicMaterial(**kwargs)
    MicromorphicMaterial(**kwargs, allow_indefinite=True)   # accepted for constitutive tests


def test_bad_numbers_are_named():
    with pytest.raises(ValueError, match=r"tau4 must be a finite number"):
        MicromorphicMaterial(**{**MAT.moduli(), "tau4": float("nan")})
    with pytest.raises(ValueError, match=r"micro_inertia = 0.0 violates micro_inertia > 0"):
        MicromorphicMaterial(**MAT.moduli(), micro_inertia=0.0)
    with pytest.raises(TypeError, match="takes a MicromorphicMaterial"):
        Micromorphic(MicropolarMaterial(lam=1.0, mu=1.0, kappa=0.5))


@pytest.mark.parametrize("d", [2, 3])
def test_rigid_modes_are_stress_free(d):
    """Each rotation mode (u = W x, phi = W) costs no energy; translations come first."""
    modes = Micromorphic.rigid_modes(d)
    assert len(modes) == (3 if d == 2 else 6)
    x = np.random.default_rng(0).normal(size=(3, 4))
    for k, (u_mode, phi_mode) in enumerate(modes):
        u = u_mode(x)
        if k < d:
            assert phi_mode is None and np.allclose(u, np.eye(d)[k][:, None])
            continue
        grad_u = np.linalg.lstsq(np.vstack([x[:d], np.ones(4)]).T, u.T, rcond=None)[0][:d].T
        W = phi_mode(x)[:, 0].reshape(d, d)
        assert np.allclose(W, -W.T) and np.allclose(grad_u, W)
        for out in micromorphic_stresses(grad_u, np.eye(d) + W, np.zeros((d, d, d)), MAT):
            assert np.abs(out).max() < 1e-12


# ---- UFL = numpy ------------------------------------------------------------------------

@pytest.mark.parametrize("d", [2, 3])
def test_ufl_stresses_equal_the_material_point_law(d):
    """u = H x, phi = P + Q x are exact in P1: the UFL stresses at a point equal the numpy
    law there (an indefinite set, so every modulus is exercised)."""
    rng = np.random.default_rng(3)
    p = dict(zip(NAMES, rng.normal(size=18), strict=True))
    mat = MicromorphicMaterial(**p, allow_indefinite=True)
    domain = (mesh.create_unit_square(MPI.COMM_SELF, 1, 1) if d == 2
              else mesh.create_unit_cube(MPI.COMM_SELF, 1, 1, 1))
    model = Micromorphic(mat)
    model.bind(domain)
    H, P, Q = rng.normal(size=(d, d)), rng.normal(size=(d, d)), rng.normal(size=(d, d, d))
    Vu = fem.functionspace(domain, ("Lagrange", 1, (d,)))
    Vp = fem.functionspace(domain, ("Lagrange", 1, (d, d)))
    u, phi = fem.Function(Vu), fem.Function(Vp)
    u.interpolate(lambda x: H @ x[:d])
    phi.interpolate(lambda x: (P[:, :, None] + np.einsum("ijk,kn->ijn", Q, x[:d])).reshape(d * d, -1))
    X = np.full((1, d), 1.0 / (d + 1))   # a point of the reference cell
    cell = np.array([0], dtype=np.int32)
    x_phys = fem.Expression(ufl.SpatialCoordinate(domain), X).eval(domain, cell).reshape(-1)[:d]
    sig, s, m = micromorphic_stresses(H, np.eye(d) + P + Q @ x_phys, Q, mat)
    for name, ref in zip(("sigma", "micro_stress", "higher_order_stress"), (sig, s, m), strict=True):
        expr = model.stresses((u, phi), {})[name]
        got = fem.Expression(expr, X).eval(domain, cell).reshape(ref.shape)
        assert np.abs(got - ref).max() < 1e-12 * (1 + np.abs(ref).max()), name


# ---- patch test -------------------------------------------------------------------------

@pytest.mark.mpi
@pytest.mark.parametrize("gdim", [2, 3])
def test_homogeneous_state_is_reproduced(gdim):
    """Boundary values of u = G x and a constant phi = Phi that makes the micro-stress
    balance hold (s - sigma = 0) are reproduced to round-off inside a distorted mesh."""
    comm = MPI.COMM_WORLD
    rng = np.random.default_rng(5)
    if gdim == 2:
        domain = mesh.create_unit_square(comm, 4, 4, diagonal=mesh.DiagonalType.crossed)
    else:
        domain = mesh.create_unit_cube(comm, 2, 2, 2)
    x = domain.geometry.x
    inner = np.all((x[:, :gdim] > 1e-8) & (x[:, :gdim] < 1 - 1e-8), axis=1)
    # a distortion that is a function of the position: ghost nodes move as their owners
    wobble = np.sin(7.0 * x[inner, :gdim] + 3.0 * x[inner, :gdim][:, ::-1] + 1.0)
    x[inner, :gdim] += 0.06 * wobble
    G = rng.normal(size=(gdim, gdim)) * 1e-3
    # s - sigma is affine in phi: solve s - sigma = 0 for Phi with the material-point law
    zero3 = np.zeros((gdim,) * 3)

    def residual(Phi):
        sig, s, _ = micromorphic_stresses(G, np.eye(gdim) + Phi.reshape(gdim, gdim), zero3, MAT)
        return (s - sig).reshape(-1)

    r0 = residual(np.zeros(gdim * gdim))
    J = np.column_stack([residual(e) - r0 for e in np.eye(gdim * gdim)])
    Phi = np.linalg.solve(J, -r0)
    assert np.abs(residual(Phi)).max() < 1e-15
    problem = ContinuumProblem(domain, Micromorphic(MAT), prefix=f"mmpatch{gdim}_")
    problem.fix(everywhere, "u", lambda p: G @ p[:gdim])
    problem.fix(everywhere, "phi", lambda p: np.tile(Phi[:, None], p.shape[1]))
    problem.solve()
    u, ph = problem.w.sub(0).collapse(), problem.w.sub(1).collapse()
    xu = u.function_space.tabulate_dof_coordinates()[:, :gdim]
    err_u = np.abs(u.x.array.reshape(-1, gdim) - xu @ G.T).max(initial=0.0)
    err_phi = np.abs(ph.x.array.reshape(-1, gdim * gdim) - Phi).max(initial=0.0)
    assert comm.allreduce(err_u, MPI.MAX) < 1e-14
    assert comm.allreduce(err_phi, MPI.MAX) < 1e-14
    # no reaction beyond the boundary tractions of the constant stress: net force zero
    assert np.abs(problem.reaction(everywhere, "u")).max() < 1e-14


# ---- manufactured solutions ---------------------------------------------------------------

def _exact(domain):
    x = ufl.SpatialCoordinate(domain)
    u = ufl.as_vector([ufl.sin(np.pi * x[0]) * ufl.cos(x[1]), x[0] * x[1] ** 2])
    phi = ufl.as_matrix([[ufl.cos(x[0] + 2 * x[1]), x[0] * x[1]],
                         [ufl.sin(x[1]) * x[0], ufl.exp(x[0] - x[1])]])
    u_np = lambda p: np.vstack([np.sin(np.pi * p[0]) * np.cos(p[1]), p[0] * p[1] ** 2])  # noqa: E731
    phi_np = lambda p: np.vstack([np.cos(p[0] + 2 * p[1]), p[0] * p[1],  # noqa: E731
                                  np.sin(p[1]) * p[0], np.exp(p[0] - p[1])])
    return u, phi, u_np, phi_np


def _mms_errors(n, degree, neumann):
    """Errors of the manufactured solution; with ``neumann`` the edge x = 1 carries the
    traction ``sigma n`` and the double traction ``m n`` of the exact fields (the index
    conventions of :mod:`granfe.models.micromorphic`), the other edges the exact values."""
    domain = mesh.create_unit_square(MPI.COMM_WORLD, n, n)
    u_ex, phi_ex, u_np, phi_np = _exact(domain)
    problem = ContinuumProblem(domain, Micromorphic(MAT), degree=degree,
                               prefix=f"mms{n}_{degree[0]}{degree[1]}{int(neumann)}_")
    sigma, s, m = stresses(u_ex, phi_ex, problem.constants)
    problem.body_load("u", -ufl.div(sigma))
    problem.body_load("phi", s - sigma - ufl.div(m))
    if neumann:
        def right(x):
            return np.isclose(x[0], 1.0)

        def held(x):
            return np.isclose(x[0], 0.0) | np.isclose(x[1], 0.0) | np.isclose(x[1], 1.0)

        normal = ufl.FacetNormal(domain)
        problem.traction(right, ufl.dot(sigma, normal))
        problem.surface_load(right, "phi", ufl.dot(m, normal))
    else:
        held = everywhere
    problem.fix(held, "u", u_np)
    problem.fix(held, "phi", phi_np)
    problem.solve()
    u, phi = ufl.split(problem.w)
    dx = ufl.dx(metadata={"quadrature_degree": 8})

    def norm(e):
        return np.sqrt(domain.comm.allreduce(fem.assemble_scalar(fem.form(ufl.inner(e, e) * dx)),
                                             MPI.SUM))

    return np.array([norm(u - u_ex), norm(ufl.grad(u - u_ex)), norm(phi - phi_ex),
                     norm(ufl.grad(phi - phi_ex))])


# (u_L2, u_H1, phi_L2, phi_H1), observed (8 -> 16): P2/P1 with the Neumann edge 2.22, 1.99,
# 1.98, 0.99 (all Dirichlet: 2.46, 2.00, 1.99, 1.00); P2/P2 3.00, 2.00, 3.00, 2.00. u_L2 of
# P2/P1 is limited by phi's O(h^2) L2 error entering through E = grad u^T + phi.
# 3D (not run here; unit cube 4 -> 8): P2/P1 2.65, 2.00, 2.00, 1.00; P2/P2 (4 -> 6) 3, 2, 3, 2.
EXPECTED = {((2, 1), True): (2, 2, 2, 1), ((2, 2), False): (3, 2, 3, 2)}


@pytest.mark.parametrize("degree, neumann", list(EXPECTED))
def test_manufactured_rates_2d(degree, neumann):
    errs = [_mms_errors(n, degree, neumann) for n in (4, 8, 16)]
    rates = np.log2(errs[-2] / errs[-1])
    assert np.all(rates > np.array(EXPECTED[degree, neumann]) - 0.1), rates


# ---- the micropolar limit ----------------------------------------------------------------

def _shear_layer(p, delta):
    """Bottom (y = 0) clamped, top (y = 1) displaced by delta along x, both holding the
    micro-structure (phi = 0); the sides free."""
    bottom = lambda x: np.isclose(x[1], 0.0)  # noqa: E731
    top = lambda x: np.isclose(x[1], 1.0)  # noqa: E731
    p.fix(bottom, "u")
    p.fix(top, "u", (delta,) + (0.0,) * (p.gdim - 1))
    fix_zero(p, bottom, "phi")
    fix_zero(p, top, "phi")
    p.solve()
    return p


@pytest.mark.mpi
@pytest.mark.parametrize("gdim", [2, 3])
def test_rotation_constrained_micromorphic_is_micropolar(gdim):
    """With penalty P on sym(phi) (through mu and sigma) and the moduli of
    :meth:`MicromorphicMaterial.micropolar_limit`, the micromorphic sheared block tends to
    the micropolar one on the same mesh and elements; the gap closes like 1 / P. The
    micro-rotation is the axial vector of phi: phi_z = phi_yx (= -phi_xy), in 3D also
    phi_x = phi_zy, phi_y = phi_xz."""
    comm = MPI.COMM_WORLD
    if gdim == 2:
        domain = mesh.create_rectangle(comm, [[0.0, 0.0], [2.0, 1.0]], [12, 6])
        axial = [(1, 0)]
    else:
        domain = mesh.create_box(comm, [[0.0, 0.0, 0.0], [1.5, 1.0, 0.5]], [6, 4, 2])
        axial = [(2, 1), (0, 2), (1, 0)]
    lam, mu, kappa, gamma, delta = 1.5, 1.0, 0.8, 0.05, 0.01
    mp = _shear_layer(MicropolarProblem(domain, MicropolarMaterial(
        lam=lam, mu=mu, kappa=kappa, gamma=gamma), prefix=f"mplim{gdim}_"), delta)
    S = fem.functionspace(domain, ("Lagrange", 1))
    Vu = mp.w.sub(0).collapse().function_space

    def values(f, space=S):
        g = fem.Function(space)
        g.interpolate(f)
        return g.x.array.copy()

    def gap(a, b, scale):
        return comm.allreduce(np.abs(a - b).max(initial=0.0), MPI.MAX) / scale

    u_ref = values(mp.w.sub(0), Vu)
    rot_ref = ([values(mp.w.sub(1))] if gdim == 2
               else [values(mp.w.sub(1).sub(k)) for k in range(3)])
    scale_u = comm.allreduce(np.abs(u_ref).max(), MPI.MAX)
    scale_phi = comm.allreduce(max(np.abs(r).max() for r in rot_ref), MPI.MAX)
    assert scale_phi > 1e-3 * delta      # the rotation is not trivial
    gaps = []
    for P in (1e4, 1e6):
        mat = MicromorphicMaterial.micropolar_limit(lam, mu, kappa, gamma, penalty=P)
        mm = _shear_layer(ContinuumProblem(domain, Micromorphic(mat), prefix=f"mmlim{gdim}{P:g}_"),
                          delta)
        phi = [[values(mm.w.sub(1).sub(gdim * i + j)) for j in range(gdim)] for i in range(gdim)]
        gaps.append((gap(values(mm.w.sub(0), Vu), u_ref, scale_u),
                     max(gap(phi[i][j], r, scale_phi) for (i, j), r in zip(axial, rot_ref, strict=True)),
                     max(gap(phi[i][j], -phi[j][i], scale_phi)
                         for i in range(gdim) for j in range(i, gdim))))
    (u1, r1, s1), (u2, r2, s2) = gaps
    # measured (u, rotation, sym phi), P2/P1: 2D 12 x 6: P = 1e4: 1.2e-6, 6.8e-5, 1.8e-4;
    # P = 1e6: 1.2e-8, 6.8e-7, 1.8e-6. 3D 6 x 4 x 2: 1.5e-6, 7.3e-5, 1.6e-4; 1.5e-8, 7.3e-7, 1.6e-6
    assert u2 < 1e-7 and r2 < 1e-5 and s2 < 1e-5, gaps
    assert min(u1 / u2, r1 / r2, s1 / s2) > 90, gaps


# ---- micro-inertia ----------------------------------------------------------------------

def test_homogeneous_micro_rotation_oscillates_at_the_micro_frequency():
    """u = 0, phi = Phi0 cos(w t) with Phi0 skew is an exact homogeneous solution with
    ``rho i w^2 = kappa - nu`` (s - sigma = (kappa - nu) phi); the trapezoidal rule
    (rho_inf = 1) follows it with the frequency ``2 atan(w dt / 2) / dt`` to round-off."""
    from dataclasses import replace

    from granfe.dynamics import GeneralizedAlpha

    mat = replace(MAT, rho=2.0, micro_inertia=0.5)
    omega = np.sqrt((mat.kappa - mat.nu) / (mat.rho * mat.micro_inertia))
    domain = mesh.create_unit_square(MPI.COMM_WORLD, 2, 2)
    problem = ContinuumProblem(domain, Micromorphic(mat), prefix="mmosc_")
    problem.fix(everywhere, "u")
    Phi0 = np.array([0.0, -1e-3, 1e-3, 0.0])
    problem.w.sub(1).interpolate(lambda x: np.tile(Phi0[:, None], x.shape[1]))
    dt = 0.1
    stepper = GeneralizedAlpha(problem, dt, rho_inf=1.0)
    stepper.initialize_acceleration()
    E0 = sum(stepper.energies())
    omega_h = 2 * np.arctan(omega * dt / 2) / dt
    for n in range(1, 41):
        stepper.step()
        phi = problem.w.sub(1).collapse().x.array.reshape(-1, 4)
        err = np.abs(phi - Phi0 * np.cos(omega_h * n * dt)).max(initial=0.0)
        assert domain.comm.allreduce(err, MPI.MAX) < 1e-15
    assert sum(stepper.energies()) == pytest.approx(E0, rel=1e-12)
    assert E0 == pytest.approx(0.5 * (mat.kappa - mat.nu) * (Phi0 @ Phi0), rel=1e-12)


# ---- MPI --------------------------------------------------------------------------------

def _cantilever(comm):
    domain = mesh.create_rectangle(comm, [[0.0, 0.0], [1.0, 0.25]], [12, 3])
    problem = ContinuumProblem(domain, Micromorphic(MAT), prefix=f"mmcant{comm.size}_")
    problem.fix(lambda x: np.isclose(x[0], 0.0), "u")
    fix_zero(problem, lambda x: np.isclose(x[0], 0.0), "phi")
    problem.traction(lambda x: np.isclose(x[0], 1.0), (1e-3, -2e-3))
    problem.solve()
    return problem


@pytest.mark.mpi
def test_serial_equals_parallel():
    from granfe.probe import probe

    pts = np.array([[1.0, 0.125, 0.0], [0.5, 0.25, 0.0], [0.3, 0.1, 0.0]])
    world, alone = _cantilever(MPI.COMM_WORLD), _cantilever(MPI.COMM_SELF)
    clamp = lambda x: np.isclose(x[0], 0.0)  # noqa: E731
    assert world.reaction(clamp, "u") == pytest.approx([-0.25e-3, 0.5e-3], rel=1e-10)
    # the rigid rotation (u = W x, phi = W) measures the moment: -(1.0 * -0.5e-3 - 0.125 * 0.25e-3)
    assert world.reaction_moment(clamp) == pytest.approx(0.5e-3 + 0.125 * 0.25e-3, rel=1e-10)
    for sub in (0, 1):
        a = probe(world.w.sub(sub).collapse(), pts)
        b = probe(alone.w.sub(sub).collapse(), pts)
        assert np.allclose(a, b, rtol=1e-11, atol=1e-13 * np.abs(b).max())
