"""Finite-strain micromorphic elasticity (reference configuration): the material-point
stresses against finite differences of an independently built energy, the power identity
of the reference stresses, objectivity, the small-strain limit (material point and
boundary-value problem), UFL = numpy, homogeneous uniaxial stress against the Saint
Venant-Kirchhoff closed form, and quadratic convergence of SNES."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
import ufl
from dolfinx import fem, mesh
from micromorphic_reference import tensors

from granfe.models.micromorphic import Micromorphic, MicromorphicMaterial, micromorphic_stresses
from granfe.models.micromorphic_finite import (
    MicromorphicFiniteStrain,
    micromorphic_finite_energy,
    micromorphic_finite_nominal_stresses,
    micromorphic_finite_stresses,
    nominal_stresses,
    push_forward,
    to_tardigrade_order,
)
from granfe.problem import ContinuumProblem

NAMES = ("lam", "mu", "eta", "tau", "kappa", "nu", "sigma") + tuple(f"tau{i}" for i in range(1, 12))
MAT = MicromorphicMaterial(lam=2.0, mu=1.0, eta=0.5, tau=0.2, kappa=1.5, nu=0.3, sigma=0.1,
                           tau1=0.1, tau2=0.05, tau3=0.2, tau4=0.15, tau5=0.05, tau6=0.1,
                           tau7=1.0, tau8=0.2, tau9=0.1, tau10=0.15, tau11=0.05)


def _random_material(seed):
    p = dict(zip(NAMES, np.random.default_rng(seed).normal(size=18), strict=True))
    return p, MicromorphicMaterial(**p, allow_indefinite=True)


def _random_state(rng, d, scale=0.3):
    eye = np.eye(d)
    return (scale * rng.normal(size=(d, d)), eye + scale * rng.normal(size=(d, d)),
            scale * rng.normal(size=(d, d, d)))


def _energy(grad_u, chi, grad_chi, p):
    """psi of the issue: E = (F^T F - I)/2, Etilde = F^T chi - I, Gamma_IJK = F_iI chi_iJ,K,
    psi = E:A:E/2 + Etilde:B:Etilde/2 + Gamma:C:Gamma/2 + E:D:Etilde, with full tensors."""
    d = len(grad_u)
    A, B, C, D = tensors(p, d)
    F = np.eye(d) + grad_u
    E, Et = (F.T @ F - np.eye(d)) / 2, F.T @ chi - np.eye(d)
    G = np.einsum("iI,iJK->IJK", F, grad_chi)
    return (np.einsum("ij,ijkl,kl", E, A, E) / 2 + np.einsum("ij,ijkl,kl", Et, B, Et) / 2
            + np.einsum("ijk,ijkpqr,pqr", G, C, G) / 2 + np.einsum("ij,ijkl,kl", E, D, Et))


def _complex_step(f, X, h=1e-30):
    """df/dX by complex steps, Im f(X + i h e) / h: no cancellation, so exact to round-off
    (the energy is a polynomial, evaluated by einsum without conjugation)."""
    out = np.zeros(X.shape)
    for idx in np.ndindex(X.shape):
        Xc = X.astype(complex)
        Xc[idx] += 1j * h
        out[idx] = f(Xc).imag / h
    return out


# ---- the material-point law -------------------------------------------------------------

@pytest.mark.parametrize("d", [2, 3])
def test_nominal_stresses_are_energy_derivatives(d):
    """P = dpsi/dF, Q = dpsi/dchi, R = dpsi/d grad chi against complex-step derivatives of
    the energy built from the full tensors (an indefinite random set: every modulus
    enters), to round-off; and S = F^-1 P, R = F M."""
    p, mat = _random_material(11 + d)
    rng = np.random.default_rng(d)
    grad_u, chi, G = _random_state(rng, d)
    assert micromorphic_finite_energy(grad_u, chi, G, mat) == pytest.approx(
        _energy(grad_u, chi, G, p), rel=1e-12)
    P, Q, R = micromorphic_finite_nominal_stresses(grad_u, chi, G, mat)
    tol = 1e-13 * (1 + np.abs(P).max())
    assert np.abs(_complex_step(lambda X: _energy(X, chi, G, p), grad_u) - P).max() < tol
    assert np.abs(_complex_step(lambda X: _energy(grad_u, X, G, p), chi) - Q).max() < tol
    assert np.abs(_complex_step(lambda X: _energy(grad_u, chi, X, p), G) - R).max() < tol
    S, Sigma, M = micromorphic_finite_stresses(grad_u, chi, G, mat)
    F = np.eye(d) + grad_u
    assert np.allclose(F @ S, P, rtol=0, atol=1e-13 * np.abs(P).max())
    assert np.allclose(np.einsum("iI,IJK->iJK", F, M), R, rtol=0, atol=1e-13 * np.abs(R).max())
    assert np.array_equal(Sigma, Sigma.T)


@pytest.mark.parametrize("d", [2, 3])
def test_reference_stresses_satisfy_the_power_identity(d):
    """For random rates (F', chi', grad chi'), the pushed-forward S, Sigma, M give
    J [sigma:(grad v - nu) + s:nu + m:grad nu] = d psi/dt (complex-step derivative of the
    independent energy along the rates), nu = chi' chi^-1 and spatial gradients."""
    p, mat = _random_material(21 + d)
    rng = np.random.default_rng(30 + d)
    grad_u, chi, G = _random_state(rng, d)
    dF, dchi, dG = rng.normal(size=(d, d)), rng.normal(size=(d, d)), rng.normal(size=(d, d, d))
    h = 1e-30
    psi_dot = _energy(grad_u + 1j * h * dF, chi + 1j * h * dchi, G + 1j * h * dG, p).imag / h
    sigma, s, m = push_forward(grad_u, chi, *micromorphic_finite_stresses(grad_u, chi, G, mat))
    F = np.eye(d) + grad_u
    Fi, chii, J = np.linalg.inv(F), np.linalg.inv(chi), np.linalg.det(F)
    L, nu = dF @ Fi, dchi @ chii
    # nu_ij,K = chi'_iA,K chi^-1_Aj - chi'_iA chi^-1_AB chi_Bc,K chi^-1_cj, then ,k = ,K F^-1_Kk
    dnu = np.einsum("ijK,Kk->ijk", np.einsum("iAK,Aj->ijK", dG, chii)
                    - np.einsum("iA,AB,BcK,cj->ijK", dchi, chii, G, chii), Fi)
    power = J * (np.einsum("ij,ij", sigma, L - nu) + np.einsum("ij,ij", s, nu)
                 + np.einsum("ijk,ijk", m, dnu))
    assert power == pytest.approx(psi_dot, rel=1e-12)


@pytest.mark.parametrize("d", [2, 3])
def test_objectivity(d):
    """A superposed rigid rotation (F, chi, grad chi) -> (R F, R chi, R grad chi) leaves the
    reference stresses unchanged and rotates the current ones."""
    _, mat = _random_material(40 + d)
    rng = np.random.default_rng(41)
    grad_u, chi, G = _random_state(rng, d)
    Rot, _ = np.linalg.qr(rng.normal(size=(d, d)))
    if np.linalg.det(Rot) < 0:   # a proper rotation
        Rot[:, 0] *= -1
    F = np.eye(d) + grad_u
    rotated = (Rot @ F - np.eye(d), Rot @ chi, np.einsum("ij,jJK->iJK", Rot, G))
    ref = micromorphic_finite_stresses(grad_u, chi, G, mat)
    got = micromorphic_finite_stresses(*rotated, mat)
    for a, b in zip(ref, got, strict=True):
        assert np.abs(a - b).max() < 1e-12 * (1 + np.abs(a).max())
    # a finite rigid rotation (F = chi = R, grad chi = 0) is stress-free
    for out in micromorphic_finite_stresses(Rot - np.eye(d), Rot, np.zeros((d, d, d)), mat):
        assert np.abs(out).max() < 1e-12
    sigma, s, m = push_forward(grad_u, chi, *ref)
    sigma_r, s_r, m_r = push_forward(rotated[0], rotated[1], *got)
    assert np.allclose(sigma_r, Rot @ sigma @ Rot.T, rtol=0, atol=1e-12 * np.abs(sigma).max())
    assert np.allclose(m_r, np.einsum("ia,jb,kc,abc->ijk", Rot, Rot, Rot, m), rtol=0,
                       atol=1e-12 * np.abs(m).max())


@pytest.mark.parametrize("d", [2, 3])
def test_small_strain_limit_of_the_material_point_law(d):
    """Under a load scaled by e, S, Sigma, M differ from the small-strain sigma, s, m by
    O(e^2): relative differences O(e), falling tenfold from e = 1e-3 to 1e-4. Tardigrade's
    order of the same stresses is a transposition and an index cycle."""
    _, mat = _random_material(50 + d)
    rng = np.random.default_rng(51)
    grad_u, chi, G = _random_state(rng, d, scale=1.0)
    rel = []
    for e in (1e-3, 1e-4):
        args = (e * grad_u, np.eye(d) + e * (chi - np.eye(d)), e * G)
        fin, small = micromorphic_finite_stresses(*args, mat), micromorphic_stresses(*args, mat)
        rel.append(max(np.abs(a - b).max() / np.abs(b).max() for a, b in zip(fin, small, strict=True)))
    assert rel[0] < 30 * 1e-3 and 8 < rel[0] / rel[1] < 12
    S, Sigma, M = fin
    PK2, Sigma_t, M_t = to_tardigrade_order(S, Sigma, M)
    assert np.array_equal(PK2, S.T) and M_t[0, 1, d - 1] == M[1, d - 1, 0]


def test_model_declarations():
    """The finite-strain model takes the small-strain material (with its Smith check), has
    the small-strain model's fields and rigid modes, and is nonlinear."""
    with pytest.raises(ValueError, match="mu > 0"):
        MicromorphicMaterial(**{**MAT.moduli(), "mu": -1.0})
    with pytest.raises(TypeError, match="takes a MicromorphicMaterial"):
        MicromorphicFiniteStrain(object())
    model = MicromorphicFiniteStrain(MAT)
    assert model.linear is False and model.name == "micromorphic_finite_strain"
    for d in (2, 3):
        assert model.fields(d) == Micromorphic.fields(d)
        assert len(model.rigid_modes(d)) == len(Micromorphic.rigid_modes(d))
    domain = mesh.create_unit_cube(MPI.COMM_SELF, 1, 1, 1)
    model.bind(domain)
    V = fem.functionspace(domain, ("Lagrange", 1, (3,)))
    W = fem.functionspace(domain, ("Lagrange", 1, (3, 3)))
    u, phi = fem.Function(V), fem.Function(W)
    assert {"von_mises", "J", "sigma_xy", "phi_zz"} <= set(model.plot_fields((u, phi), {}))
    assert set(model.stresses((u, phi), {})) == {"pk2", "micro_stress", "higher_order_stress",
                                                  "cauchy"}


# ---- UFL = numpy ------------------------------------------------------------------------

@pytest.mark.parametrize("d", [2, 3])
def test_ufl_stresses_equal_the_material_point_law(d):
    """u = H x, phi = P0 + Q x are exact in P1: the UFL PK2, Sigma, M, the Cauchy stress
    and the residual's nominal stresses equal the numpy law at a point."""
    _, mat = _random_material(60 + d)
    rng = np.random.default_rng(61)
    domain = (mesh.create_unit_square(MPI.COMM_SELF, 1, 1) if d == 2
              else mesh.create_unit_cube(MPI.COMM_SELF, 1, 1, 1))
    model = MicromorphicFiniteStrain(mat)
    model.bind(domain)
    H, P0, Q = 0.3 * rng.normal(size=(d, d)), 0.3 * rng.normal(size=(d, d)), 0.3 * rng.normal(size=(d, d, d))
    Vu = fem.functionspace(domain, ("Lagrange", 1, (d,)))
    Vp = fem.functionspace(domain, ("Lagrange", 1, (d, d)))
    u, phi = fem.Function(Vu), fem.Function(Vp)
    u.interpolate(lambda x: H @ x[:d])
    phi.interpolate(lambda x: (P0[:, :, None] + np.einsum("ijk,kn->ijn", Q, x[:d])).reshape(d * d, -1))
    X = np.full((1, d), 1.0 / (d + 1))
    cell = np.array([0], dtype=np.int32)
    x_phys = fem.Expression(ufl.SpatialCoordinate(domain), X).eval(domain, cell).reshape(-1)[:d]
    chi = np.eye(d) + P0 + Q @ x_phys
    S, Sigma, M = micromorphic_finite_stresses(H, chi, Q, mat)
    sigma = push_forward(H, chi, S, Sigma, M)[0]
    P, Qn, R = micromorphic_finite_nominal_stresses(H, chi, Q, mat)
    out = model.stresses((u, phi), {})
    pairs = [(out["pk2"], S), (out["micro_stress"], Sigma), (out["higher_order_stress"], M),
             (out["cauchy"], sigma), *zip(nominal_stresses(u, phi, model.constants), (P, Qn, R),
                                              strict=True)]
    psi = micromorphic_finite_energy(H, chi, Q, mat)
    # one compiled expression for all of them, the stored energy last
    flat = ufl.as_vector([e[idx] for e, ref in pairs for idx in np.ndindex(ref.shape)]
                         + [model.stored_energy((u, phi), {})])
    got = fem.Expression(flat, X, jit_options=model.jit_options).eval(domain, cell).reshape(-1)
    ref = np.concatenate([r.reshape(-1) for _, r in pairs] + [[psi]])
    assert np.abs(got - ref).max() < 1e-12 * (1 + np.abs(ref).max())


# ---- boundary-value problems ------------------------------------------------------------

def _svk_uniaxial(stretch, lam, mu):
    """Saint Venant-Kirchhoff uniaxial stress: lateral stretch from S_22 = 0, then S_11 and
    the nominal stress P_11 = stretch S_11."""
    E1 = (stretch**2 - 1) / 2
    E2 = -lam / (2 * (lam + mu)) * E1
    S11 = mu * (3 * lam + 2 * mu) / (lam + mu) * E1
    return np.sqrt(1 + 2 * E2), S11, stretch * S11


def _relaxed_svk(p):
    """Homogeneous states with Gamma = 0 and chi free: T = B Etilde + D^T E = 0 gives
    Etilde = -B^-1 D^T E and psi = E:(A - D B^-1 D^T):E/2, an isotropic SVK energy. Returns
    its (lam, mu) and the map E -> Etilde (9 x 9), from the full tensors. B = 0 (chi held):
    A itself."""
    A, B, _, D = tensors(p, 3)
    A, B, D = A.reshape(9, 9), B.reshape(9, 9), D.reshape(9, 9)
    if not np.any(B):
        return A[0, 4], A[1, 1], np.zeros((9, 9))
    to_micro = -np.linalg.solve(B, D.T)
    A_eff = A + D @ to_micro
    lam, mu = A_eff[0, 4], (A_eff[1, 1] + A_eff[1, 3]) / 2
    assert np.isclose(A_eff[0, 0], lam + 2 * mu, rtol=1e-12)   # isotropic
    return lam, mu, to_micro


LAM, MU = 1.2e6, 0.8e6   # Pa
VARIANTS = {
    # every modulus but lam, mu zero; phi held at zero (chi undetermined otherwise)
    "lam_mu_only": dict({k: 0.0 for k in NAMES}, lam=LAM, mu=MU),
    # admissible B and C, D = 0: chi relaxes to F^-T (Etilde = 0), psi is SVK(lam, mu)
    "micro_relaxed": dict({k: v * 1e6 for k, v in MAT.moduli().items()}, lam=LAM, mu=MU,
                          tau=0.0, sigma=0.0),
    # all 18 moduli: chi relaxes to Etilde = -B^-1 D^T E, psi is SVK(lam_eff, mu_eff)
    "coupled": {k: v * 1e6 for k, v in MAT.moduli().items()},
}


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_uniaxial_stress_matches_saint_venant_kirchhoff(variant):
    """Unit cube (2 x 2 x 2 cells, P1 / P1), symmetry planes at x, y, z = 0,
    u_x = stretch - 1 on x = 1, lateral faces traction-free, stretches 1.15 then 1.3: the
    nominal stress (reaction on x = 1), the lateral stretch and chi against the Saint
    Venant-Kirchhoff closed form (of the relaxed moduli); the Newton iterations of the
    second step converge quadratically."""
    comm = MPI.COMM_WORLD
    p = VARIANTS[variant]
    mat = MicromorphicMaterial(**p, allow_indefinite=variant == "lam_mu_only")
    lam, mu, to_micro = _relaxed_svk(p)
    domain = mesh.create_unit_cube(comm, 2, 2, 2)
    problem = ContinuumProblem(domain, MicromorphicFiniteStrain(mat), degree=(1, 1),
                               prefix=f"mmfuni_{variant}_")
    problem.fix(lambda x: np.isclose(x[0], 0.0), "u_x")
    problem.fix(lambda x: np.isclose(x[1], 0.0), "u_y")
    problem.fix(lambda x: np.isclose(x[2], 0.0), "u_z")
    pull = problem.fix(lambda x: np.isclose(x[0], 1.0), "u_x", 0.0)
    if variant == "lam_mu_only":
        problem.fix_everywhere("phi")
    iterations = []
    for stretch in (1.15, 1.3):
        pull.value = stretch - 1.0
        if stretch == 1.3:
            problem.snes.setConvergenceHistory()
        iterations.append(problem.solve())
    history = problem.snes.getConvergenceHistory()[0]
    lateral, _, P11 = _svk_uniaxial(1.3, lam, mu)
    force = problem.reaction(lambda x: np.isclose(x[0], 1.0), "u_x")   # reference area 1
    assert abs(force / P11 - 1) < 1e-8   # the issue asks for 0.5 %
    u = problem.w.sub(0).collapse()
    top = np.isclose(u.function_space.tabulate_dof_coordinates()[:, 1], 1.0)
    assert np.allclose(u.x.array.reshape(-1, 3)[top, 1], lateral - 1.0, rtol=0, atol=1e-10)
    F = np.diag([1.3, lateral, lateral])
    Etilde = (to_micro @ ((F.T @ F - np.eye(3)) / 2).reshape(9)).reshape(3, 3)
    phi = problem.w.sub(1).collapse().x.array.reshape(-1, 3, 3)
    expected = 0.0 if variant == "lam_mu_only" else np.linalg.inv(F).T @ (np.eye(3) + Etilde) - np.eye(3)
    assert np.abs(phi - expected).max() < 1e-10
    # quadratic convergence: few iterations, each residual ~ the square of the previous one
    assert iterations[1] <= 6
    r = history / history[0]
    assert (r < 1e-3).any()
    k = int(np.argmax(r < 1e-3))
    assert r[k + 1] < 10 * r[k] ** 2 or r[k + 1] < 1e-10


def test_small_load_equals_small_strain_model():
    """A sheared and stretched square (plane strain, all 18 moduli): the finite-strain
    solution differs from the small-strain model's by O(load^2), relative O(load)."""
    comm = MPI.COMM_WORLD
    domain = mesh.create_unit_square(comm, 3, 3)
    bottom = lambda x: np.isclose(x[1], 0.0)   # noqa: E731
    top = lambda x: np.isclose(x[1], 1.0)   # noqa: E731
    rel = []
    for delta in (1e-3, 1e-4):
        sols = []
        for model, tag in ((MicromorphicFiniteStrain(MAT), "f"), (Micromorphic(MAT), "s")):
            p = ContinuumProblem(domain, model, degree=(1, 1), prefix=f"mmfsmall_{tag}{delta:g}_")
            p.fix(bottom, "u")
            p.fix(top, "u", (delta, 0.5 * delta))
            p.fix(bottom, "phi", 0.0)
            p.fix(top, "phi", ((0.0, delta), (0.0, 0.0)))
            p.solve()
            sols.append(p.w.x.array.copy())
        rel.append(np.linalg.norm(sols[0] - sols[1]) / np.linalg.norm(sols[1]))
    assert rel[0] < 5e-3 and 7 < rel[0] / rel[1] < 13
