"""Finite-strain micromorphic Drucker-Prager. At material points: the elastic law below the
cones, the reference stresses and the levels' yield stresses as derivatives of the stored
energy, the small-strain limit (the small-strain return), objectivity, the converged state
on the cones with non-negative dissipation, the apex, a finite-strain path against an
independent integration of the rate equations, the consistent tangent. On a mesh: one
element in uniaxial compression against the point, the residual's Taylor remainder, and
the small-strain limit against the small-strain iterative model."""

from dataclasses import replace

import numpy as np
import pytest
import scipy.integrate
import scipy.linalg
import scipy.optimize
from scipy.spatial.transform import Rotation

from granfe.models.micromorphic import MicromorphicMaterial
from granfe.models.micromorphic_drucker_prager import Cone, MicromorphicDruckerPragerMaterial
from granfe.models.micromorphic_finite import micromorphic_finite_stresses
from granfe.models.micromorphic_finite_return import (
    elastic_energy,
    finite_return,
    initial_state,
    kernel_tables,
    level_stresses,
)
from granfe.models.micromorphic_return import point_return

MU, LENGTH, C = 20e6, 0.01, 10e3
L2 = MU * LENGTH**2
ELASTIC = MicromorphicMaterial(lam=20e6, mu=MU, eta=5e6, tau=0.0, kappa=15e6, nu=3e6, sigma=0.0,
                               **{f"tau{i}": 0.0 for i in range(1, 12) if i != 7}, tau7=L2)
COUPLED = replace(ELASTIC, tau=2e6, sigma=1.5e6, tau1=0.1 * L2, tau2=0.05 * L2, tau4=0.1 * L2,
                  tau8=0.05 * L2, tau11=0.02 * L2)


def material(elastic=COUPLED, c=C, friction=30.0, dilatancy=10.0, hardening=2e6, levels=None):
    cones = {"macro": Cone(c, friction, dilatancy, hardening),
             "micro": Cone(c, friction, dilatancy, hardening),
             "gradient": Cone(c * LENGTH, friction, dilatancy, hardening * LENGTH**2)}
    if levels is not None:
        cones = {k: (v if k in levels else None) for k, v in cones.items()}
    return MicromorphicDruckerPragerMaterial(elastic, **cones)


def random_fields(n, seed, size, rotate=False):
    """(grad_u, chi, grad_chi) of n points, entries ~ size (grad chi ~ size / LENGTH)."""
    rng = np.random.default_rng(seed)
    grad_u = rng.normal(size=(n, 3, 3)) * size
    chi = np.eye(3) + rng.normal(size=(n, 3, 3)) * size
    grad_chi = rng.normal(size=(n, 3, 3, 3)) * size / LENGTH
    if rotate:        # a finite rotation of the whole point: large displacement gradients
        R = Rotation.random(n, random_state=seed).as_matrix()
        grad_u = R @ (np.eye(3) + grad_u) - np.eye(3)
        chi = R @ chi
        grad_chi = np.einsum("nij,njKL->niKL", R, grad_chi)
    return grad_u, chi, grad_chi


def random_state(n, seed, size):
    """A committed plastic state (not from a loading history; the law takes any)."""
    rng = np.random.default_rng(seed)

    def sym(a):
        return (a + a.transpose(0, 2, 1)) / 2

    Fp = np.array([scipy.linalg.expm(a) for a in sym(rng.normal(size=(n, 3, 3)) * size)])
    chip = np.array([scipy.linalg.expm(a) for a in rng.normal(size=(n, 3, 3)) * size])
    return {"Fp": Fp, "chip": chip, "Gp": rng.normal(size=(n, 3, 3, 3)) * size / LENGTH,
            "eq": np.abs(rng.normal(size=(n, 5))) * size}


def relative(a, b):
    return np.max(np.abs(a - b)) / np.max(np.abs(b))


def test_below_yield_is_finite_elasticity():
    """No plastic deformation and cones out of reach: S, Sigma, M are micromorphic_finite's
    (an independent evaluation of the energy's partials) to round-off, at small strains and
    at finite strains with finite rotations."""
    mat = material(c=1e12)
    for size, rotate in ((1e-3, False), (0.05, True)):
        fields = random_fields(20, 1, size, rotate)
        S, Sigma, M, state, info = finite_return(*fields, initial_state((20,)), mat)
        S0, Sigma0, M0 = micromorphic_finite_stresses(*fields, COUPLED)
        assert np.all(info["passes"] == 1) and not info["yielding"].any()
        assert relative(S, S0) < 1e-12 and relative(Sigma, Sigma0) < 1e-12
        assert relative(M, M0) < 1e-12
        assert np.array_equal(state["Fp"], initial_state((20,))["Fp"])


def nominal(grad_u, chi, grad_chi, S, Sigma, M):
    """``(dpsi/dF, dpsi/dchi, dpsi/d grad chi)`` of the reference stresses: ``P = F S``,
    ``Q = F T`` with ``C^-1 Psi T^T = (Sigma - S)^T - (C^-1 Gamma) : M``, ``R = F M``."""
    F = np.eye(3) + grad_u
    C_ = F.T @ F
    Psi = F.T @ chi
    Gam = np.einsum("iI,iJK->IJK", F, grad_chi)
    CiPsiTt = (Sigma - S).T - np.einsum("IS,SQR,JQR->IJ", np.linalg.inv(C_), Gam, M)
    T = np.linalg.solve(np.linalg.inv(C_) @ Psi, CiPsiTt).T
    return F @ S, F @ T, np.einsum("iI,IJK->iJK", F, M)


def test_reference_stresses_are_the_energy_derivatives():
    """At a committed plastic state (finite F^p, chi^p, G^p) and finite strain, the
    nominal stresses of (S, Sigma, M) are the derivatives of the stored energy in F, chi and
    grad chi (central differences)."""
    mat = material(c=1e12)
    tab = kernel_tables(mat)
    fields = random_fields(2, 2, 0.05, rotate=True)
    state = random_state(2, 3, 0.05)
    S, Sigma, M, _, _ = finite_return(*fields, state, mat, tab)
    for n in range(2):
        one = [f[n] for f in fields]
        st = {k: v[n] for k, v in state.items()}
        for arg, exact in enumerate(nominal(*one, S[n], Sigma[n], M[n])):
            fd = np.zeros(exact.shape)
            for idx in np.ndindex(exact.shape):
                h = 1e-6 * (1.0 if arg < 2 else 1.0 / LENGTH)
                plus, minus = [a.copy() for a in one], [a.copy() for a in one]
                plus[arg][idx] += h
                minus[arg][idx] -= h
                fd[idx] = (elastic_energy(*plus, st, mat, tab)
                           - elastic_energy(*minus, st, mat, tab)) / (2 * h)
            assert relative(fd, exact) < 1e-6, (n, arg)


def advance(state, D, h):
    """The plastic state after increments ``h D`` (5, 3, 3), by scipy's expm (the flow rule
    of the module docstring)."""
    E = scipy.linalg.expm(h * (D[1] - D[0]))
    Fp = scipy.linalg.expm(h * D[0]) @ state["Fp"]
    chip = E @ state["chip"]
    Gp = np.einsum("bc,cJK->bJK", E, state["Gp"]) + h * np.einsum(
        "Cba,aJ,CK->bJK", D[2:], chip, Fp)
    return {"Fp": Fp, "chip": chip, "Gp": Gp, "eq": state["eq"]}


def test_level_stresses_are_the_conjugates_of_the_plastic_increments():
    """The levels' yield stresses t_i are the energy released per unit plastic increment:
    ``d psi / dh = -sum_i t_i : D_i`` for symmetric macro and micro increments and any slice
    increments (central differences, finite strain and plastic state)."""
    mat = material(c=1e12)
    tab = kernel_tables(mat)
    rng = np.random.default_rng(4)
    fields = random_fields(3, 5, 0.05, rotate=True)
    state = random_state(3, 6, 0.05)
    t = level_stresses(*fields, state, mat, tab)
    for n in range(3):
        one = [f[n] for f in fields]
        st = {k: v[n] for k, v in state.items()}
        D = rng.normal(size=(5, 3, 3))
        D[:2] = (D[:2] + D[:2].transpose(0, 2, 1)) / 2
        h = 1e-6
        fd = (elastic_energy(*one, advance(st, D, h), mat, tab)
              - elastic_energy(*one, advance(st, D, -h), mat, tab)) / (2 * h)
        exact = -np.sum(t[n] * D)
        assert abs(fd - exact) < 1e-6 * np.sum(np.abs(t[n] * D)), (n, fd, exact)


def small_strain_return(grad_u, chi, grad_chi, mat):
    """The small-strain model's return (micromorphic_return) of the same fields: stresses
    ``(sigma, s, m)`` and state ``(eps_p, E_p, G_p, eq)``."""
    n = len(grad_u)
    phi = chi - np.eye(3)
    x = np.concatenate([((grad_u + grad_u.transpose(0, 2, 1)) / 2).reshape(n, 9),
                        (grad_u.transpose(0, 2, 1) + phi).reshape(n, 9)]
                       + [grad_chi[:, :, :, M].reshape(n, 9) for M in range(3)], axis=1)
    tab = kernel_tables(mat)
    y, _, xp, eq, _, failed = point_return(x, np.zeros_like(x), np.zeros((n, 5)), tab.K,
                                           tab.cones, tab.has_cone, tangent=False)
    assert failed == 0
    S, T = y[:, :9].reshape(n, 3, 3), y[:, 9:18].reshape(n, 3, 3)
    m = np.stack([y[:, 18 + 9 * M: 27 + 9 * M].reshape(n, 3, 3) for M in range(3)], axis=-1)
    Gp = np.stack([xp[:, 18 + 9 * M: 27 + 9 * M].reshape(n, 3, 3) for M in range(3)], axis=-1)
    return ((S + T.transpose(0, 2, 1), S + T + T.transpose(0, 2, 1), m),
            (xp[:, :9].reshape(n, 3, 3), xp[:, 9:18].reshape(n, 3, 3), Gp, eq))


def small_strain_differences(size):
    """Relative differences of stresses and plastic states between the finite-strain and
    the small-strain returns at strains ~ size (cohesions scaled with it: all levels yield
    at most points)."""
    mat = material(c=0.3 * MU * size, hardening=0.2 * MU)
    n = 40
    fields = random_fields(n, 7, size)
    S, Sigma, M, state, info = finite_return(*fields, initial_state((n,)), mat)
    (sigma, s, m), (eps_p, E_p, G_p, eq) = small_strain_return(*fields, mat)
    assert np.all(info["passes"] > 0) and info["yielding"].mean() > 0.5
    stresses = max(relative(S, sigma), relative(Sigma, s), relative(M, m))
    # F^p - I -> eps_p, chi^p - I -> E_p - eps_p, G^p -> G_p
    states = max(relative(state["Fp"] - np.eye(3), eps_p),
                 relative(state["chip"] - np.eye(3), E_p - eps_p),
                 relative(state["Gp"], G_p), relative(state["eq"], eq))
    return stresses, states


def test_small_strain_limit_is_the_small_strain_return():
    """At strains 1e-6 and 1e-5 (coupled moduli, all five levels yielding) the stresses and
    the plastic state equal the small-strain return's to relative differences of the order
    of the strain (the neglected quadratic terms), shrinking tenfold with the strain."""
    coarse, fine = small_strain_differences(1e-5), small_strain_differences(1e-6)
    for a, b in zip(coarse, fine, strict=True):
        assert a < 20 * 1e-5 and b < 20 * 1e-6, (coarse, fine)
        assert 5 < a / b < 20, (coarse, fine)


def test_objectivity():
    """A superposed rigid rotation (F -> R F, chi -> R chi, grad chi -> R grad chi) leaves
    S, Sigma, M, the plastic state and the dissipation unchanged, at finite strain with a
    committed plastic state and yielding levels."""
    mat = material(c=0.3 * MU * 0.02, hardening=0.2 * MU)
    n = 10
    fields = random_fields(n, 8, 0.02, rotate=True)
    state = random_state(n, 9, 0.01)
    R = Rotation.random(n, random_state=10).as_matrix()
    turned = (R @ (np.eye(3) + fields[0]) - np.eye(3), R @ fields[1],
              np.einsum("nij,njKL->niKL", R, fields[2]))
    one = finite_return(*fields, state, mat)
    two = finite_return(*turned, state, mat)
    assert one[4]["yielding"].mean() > 0.5 and np.all(one[4]["passes"] > 0)
    for a, b in zip(one[:3], two[:3], strict=True):
        assert relative(b, a) < 1e-10
    for k in ("Fp", "chip", "Gp", "eq"):
        assert np.max(np.abs(two[3][k] - one[3][k])) < 1e-10 * np.max(np.abs(one[3][k]))
    assert relative(two[4]["dissipation"], one[4]["dissipation"]) < 1e-8


@pytest.mark.parametrize("dilatancy", [0.0, 30.0])
def test_on_the_cones_with_nonnegative_dissipation(dilatancy):
    """Finite strain (entries ~ 0.02, rotations) from a committed plastic state, coupled
    moduli, 100 points, nearly all levels yielding: every return converges, every level
    ends on or inside its cone (on it to 1e-11 of the point's largest stress where it yielded), the
    step's dissipation sum t_i : D_i >= 0, the stored energy drops below the trial one for
    an associated flow, and isochoric flows (no dilatancy) keep det F^p and det chi^p."""
    mat = material(c=0.3 * MU * 0.02, hardening=0.2 * MU, dilatancy=dilatancy)
    tab = kernel_tables(mat)
    n = 100
    fields = random_fields(n, 11, 0.02, rotate=True)
    state = random_state(n, 12, 0.01)
    _, _, _, new, info = finite_return(*fields, state, mat, tab)
    assert np.all(info["passes"] > 0) and info["yielding"].mean() > 0.9
    # the point's largest stress (the Newton's scale; the slices' are in Pa m)
    scale = np.max(np.abs(level_stresses(*fields, new, mat, tab)), axis=(1, 2, 3))[:, None]
    plastic = new["eq"] > state["eq"]
    assert np.all(np.abs(info["f"]) * plastic < 1e-11 * scale)
    assert np.all(info["f"] < 1e-11 * scale)
    assert np.all(info["dissipation"] >= 0) and info["dissipation"].max() > 0
    if dilatancy == 30.0:
        trial = elastic_energy(*fields, state, mat, tab)
        assert np.all(trial - info["psi"] >= 0)
    else:
        for k in ("Fp", "chip"):
            ratio = np.linalg.det(new[k]) / np.linalg.det(state[k])
            assert np.max(np.abs(ratio - 1)) < 1e-13


# ---- a finite-strain path against an independent integration ---------------------------

SVK = MicromorphicMaterial(lam=20e6, mu=MU, eta=0.0, tau=0.0, kappa=0.0, nu=0.0, sigma=0.0,
                           **{f"tau{i}": 0.0 for i in range(1, 12)}, allow_indefinite=True)
PATH_CONE = Cone(20e3, 30.0, 10.0, 1e6)


def stretches(t):
    """A non-proportional compression (15 % axially, the lateral stretches turning the
    deviator's Lode angle): principal stretches and their rates ``dlam/dt / lam``."""
    lam3 = np.array([1 + 0.12 * t**2, 1 + 0.05 * t - 0.1 * t**2, 1 - 0.15 * t])
    return lam3, np.array([0.24 * t, 0.05 - 0.2 * t, -0.15]) / lam3


def macro_stress(lam3, y):
    """The macro Mandel stress (diagonal) of the Saint Venant-Kirchhoff macro energy with
    F^p = diag(exp y), written out: ``Xi = C^e (lam tr E^e I + 2 mu E^e)``."""
    Ce = lam3**2 * np.exp(-2 * y)
    Ee = (Ce - 1) / 2
    return Ce * (SVK.lam * Ee.sum() + 2 * SVK.mu * Ee), Ce


def yield_value(xi, e):
    A, _, k0 = PATH_CONE.constants
    p = xi.mean()
    dev = xi - p
    return np.sqrt(0.5 * dev @ dev) + A * p - (k0 + PATH_CONE.hardening * e)


def rate_equations(t, state):
    """``d(ln F^p, e)/dt`` on the cone: the flow ``n`` and the multiplier from the
    consistency condition ``df/dt = 0`` (chain rule written out, no return mapping)."""
    A, B, _ = PATH_CONE.constants
    y = state[:3]
    lam3, rate = stretches(t)
    xi, Ce = macro_stress(lam3, y)
    psi = xi / Ce
    p = xi.mean()
    dev = xi - p
    tau = np.sqrt(0.5 * dev @ dev)
    df = dev / (2 * tau) + A / 3            # df / dXi
    n = dev / (2 * tau) + B / 3             # the flow (dg / dXi)
    # dXi_i/dy_j and dXi_i/dt (dCe_k = 2 Ce_k (rate_k dt - dy_k), dEe_k = dCe_k / 2)
    dXi_dy = -2 * np.diag(Ce * psi) - Ce[:, None] * (SVK.lam * Ce[None, :]
                                                      + 2 * SVK.mu * np.diag(Ce))
    w = Ce * rate
    dXi_dt = 2 * Ce * rate * psi + Ce * (SVK.lam * w.sum() + 2 * SVK.mu * w)
    gamma = -(df @ dXi_dt) / (df @ dXi_dy @ n - PATH_CONE.hardening)
    assert gamma > 0               # plastic loading all along
    return np.concatenate([gamma * n, [gamma]])


def independent_path():
    """(ln F^p, e) at t = 1: elastic up to the first yield (root of f), then the rate
    equations by scipy's DOP853 at rtol 1e-11."""
    t_y = scipy.optimize.brentq(lambda t: yield_value(macro_stress(stretches(t)[0],
                                                                   np.zeros(3))[0], 0.0),
                                1e-9, 1.0, xtol=1e-15)
    sol = scipy.integrate.solve_ivp(rate_equations, (t_y, 1.0), np.zeros(4), method="DOP853",
                                    rtol=1e-11, atol=1e-14)
    assert sol.success
    return sol.y[:3, -1], sol.y[3, -1]


def implicit_path(steps):
    """The return mapping along the same path in ``steps`` equal steps (macro cone only,
    chi = F: no micro or higher-order stress); (ln F^p, e, S_zz) at t = 1."""
    mat = MicromorphicDruckerPragerMaterial(SVK, macro=PATH_CONE)
    tab = kernel_tables(mat)
    state = initial_state()
    zero = np.zeros((3, 3, 3))
    for t in np.linspace(0, 1, steps + 1)[1:]:
        F = np.diag(stretches(t)[0])
        S, _, _, state, info = finite_return(F - np.eye(3), F, zero, state, mat, tab)
        assert info["passes"] > 0
    return np.log(np.diag(state["Fp"])), state["eq"][0], S[2, 2], state


def test_finite_strain_path_against_an_independent_integration():
    """15 % compression along a non-proportional path with the macro cone only (hardening,
    dilatancy): the backward-Euler exponential-map return converges at first order in the
    step to scipy's integration of the rate equations; 400 steps are within 0.1 %."""
    y_ref, e_ref = independent_path()
    lam3 = stretches(1.0)[0]
    xi, Ce = macro_stress(lam3, y_ref)
    S_ref = xi[2] / Ce[2] * np.exp(-2 * y_ref[2])         # S = Fp^-1 psi_E Fp^-T
    errors = []
    for steps in (100, 200, 400):
        y, e, S_zz, state = implicit_path(steps)
        errors.append(max(relative(y, y_ref), abs(e - e_ref) / e_ref,
                          abs(S_zz - S_ref) / abs(S_ref)))
    assert errors[-1] < 1e-3, errors
    assert 1.7 < errors[0] / errors[1] < 2.3 and 1.7 < errors[1] / errors[2] < 2.3, errors
    assert abs(np.linalg.det(state["Fp"]) - np.exp(y_ref.sum())) < 1e-3 * abs(y_ref.sum())
    print("path errors (100, 200, 400 steps):", errors)


def test_consistent_tangent_is_the_derivative_of_the_return():
    """The nominal stresses [P, Q, R] are F S, F T, F M of the returned stresses, and the
    consistent tangent equals central differences of the whole return (active-set loop
    included) in [grad u, phi, grad phi], at finite strain from a committed state with 13
    of the 15 levels yielding."""
    mat = material(c=0.3 * MU * 0.02, hardening=0.2 * MU)
    tab = kernel_tables(mat)
    n = 3
    fields = random_fields(n, 21, 0.02, rotate=True)
    state = random_state(n, 22, 0.01)
    S, Sigma, M, _, info = finite_return(*fields, state, mat, tab, tangent=True)
    assert info["yielding"].sum() == 13             # of the 15 levels
    for k in range(n):
        exact = np.concatenate([a.ravel() for a in nominal(*[f[k] for f in fields], S[k],
                                                           Sigma[k], M[k])])
        assert relative(info["nominal"][k], exact) < 1e-12
    x = np.concatenate([fields[0].reshape(n, 9), (fields[1] - np.eye(3)).reshape(n, 9),
                        fields[2].reshape(n, 27)], axis=1)

    def returned(x):
        return finite_return(x[:, :9].reshape(-1, 3, 3), np.eye(3) + x[:, 9:18].reshape(-1, 3, 3),
                             x[:, 18:].reshape(-1, 3, 3, 3), state, mat, tab)[4]["nominal"]

    fd = np.zeros((n, 45, 45))
    for j in range(45):
        h = 1e-6 if j < 18 else 1e-6 / LENGTH
        plus, minus = x.copy(), x.copy()
        plus[:, j] += h
        minus[:, j] -= h
        fd[:, :, j] = (returned(plus) - returned(minus)) / (2 * h)
    for k in range(n):
        assert relative(info["tangent"][k], fd[k]) < 1e-6


def test_hydrostatic_tension_returns_to_the_apex():
    """F = chi = 1.02 I (Saint Venant-Kirchhoff macro energy, macro cone with dilatancy and
    hardening): the macro level returns to its apex, F^p = exp(B dl / 3) I with ``A p = k0
    + H dl`` (a scalar equation solved by brentq), the deviator zero."""
    mat = MicromorphicDruckerPragerMaterial(SVK, macro=PATH_CONE)
    A, B, k0 = PATH_CONE.constants
    H, stretch = PATH_CONE.hardening, 1.02
    lam3 = (3 * SVK.lam + 2 * SVK.mu)

    def pressure(dl):
        Ce = stretch**2 * np.exp(-2 * B * dl / 3)
        return Ce * lam3 * (Ce - 1) / 2

    dl = scipy.optimize.brentq(lambda dl: A * pressure(dl) - k0 - H * dl, 0.0, 1.0, xtol=1e-16)
    F = stretch * np.eye(3)
    _, _, _, state, info = finite_return(F - np.eye(3), F, np.zeros((3, 3, 3)), initial_state(),
                                         mat)
    t = level_stresses(F - np.eye(3), F, np.zeros((3, 3, 3)), state, mat)[0]
    p = np.trace(t) / 3
    assert info["passes"] > 0 and info["yielding"][0] == 1
    assert np.abs(t - p * np.eye(3)).max() < 1e-10 * p
    assert abs(p / pressure(dl) - 1) < 1e-10 and abs(state["eq"][0] / dl - 1) < 1e-8
    np.testing.assert_allclose(state["Fp"], np.exp(B * dl / 3) * np.eye(3), rtol=1e-10, atol=1e-12)


# ---- the FE model: one element -----------------------------------------------------------

def uniaxial_point_driver(mat, strains):
    """The material point in uniaxial stress by itself (no mesh): for each axial
    displacement gradient u_z,z, the lateral u_x,x, u_y,y and phi (9) that make P_xx = P_yy
    = 0 and Q = 0 (scipy's hybr on the returned stresses), the plastic state committed
    step by step (the return's tangent as root's Jacobian). Returns (eq macro, P_zz) per
    step."""
    tab = kernel_tables(mat)
    state, v = initial_state(), np.zeros(11)
    out = []
    rows = np.r_[0, 4, 9:18]                 # P_xx, P_yy, Q; unknowns u_x,x, u_y,y, phi

    def fields(v, ezz):
        return np.diag([v[0], v[1], ezz]), np.eye(3) + v[2:].reshape(3, 3), np.zeros((3, 3, 3))

    for ezz in strains:
        def residual(v, ezz=ezz, state=state):
            info = finite_return(*fields(v, ezz), state, mat, tab, tangent=True)[4]
            return info["nominal"][rows] / MU, info["tangent"][np.ix_(rows, rows)] / MU

        sol = scipy.optimize.root(residual, v, jac=True, method="hybr",
                                  options={"xtol": 1e-14})
        assert np.abs(residual(sol.x)[0]).max() < 1e-12
        v = sol.x
        _, _, _, state, info = finite_return(*fields(v, ezz), state, mat, tab)
        out.append((state["eq"][0], info["nominal"][8]))
    return np.array(out), info["psi"]


def pushed(p, top, strains, components):
    """The top's prescribed displacement set to each of ``strains`` in turn and solved:
    Newton's iterations a step, and per step the macro equivalent plastic strain and the
    nominal stress ``components`` (of 45) of the element's points, which must all hold the
    same state."""
    its, out = [], []
    for e in strains:
        top.value = e
        its.append(p.solve())
        eq = p.state.owned("equivalent_plastic_strain").reshape(-1, 5)
        stress = p.state.owned("stress").reshape(-1, 45)
        assert np.ptp(eq[:, 0]) < 1e-10 * eq[:, 0].max()           # homogeneous
        out.append((eq[0, 0], *stress[0, components]))
    return its, np.array(out)


def test_one_element_uniaxial_compression_equals_the_point():
    """One trilinear hexahedron (u, phi of degree 1, 8 points), symmetry planes, the top
    pushed down 12 % in four steps, sides free, phi free, coupled moduli with all cones:
    the macro level yields (Q = 0 leaves the micro stress zero), Newton on the consistent
    tangent converges in a few iterations a step, and every point holds the material
    point's own uniaxial state (scipy root on the lateral stretches and chi) to 1e-8; the
    model's UFL stored energy at the committed state is the kernel's psi."""
    from mpi4py import MPI

    from dolfinx import fem, mesh

    from granfe.models import MODELS
    from granfe.models.micromorphic_finite_plastic import MicromorphicFiniteDruckerPrager
    from granfe.problem import ContinuumProblem

    assert MODELS["micromorphic_finite_drucker_prager"] is MicromorphicFiniteDruckerPrager

    mat = material(c=20e3)
    domain = mesh.create_unit_cube(MPI.COMM_SELF, 1, 1, 1, mesh.CellType.hexahedron)
    p = ContinuumProblem(domain, MicromorphicFiniteDruckerPrager(mat), degree=(1, 1),
                         quadrature_degree=2, prefix="mmfdp_one_")
    for axis, name in enumerate(("u_x", "u_y", "u_z")):
        p.fix(lambda x, a=axis: np.isclose(x[a], 0.0), name)
    top = p.fix(lambda x: np.isclose(x[2], 1.0), "u_z", 0.0)
    strains = [-0.02, -0.05, -0.08, -0.12]
    its, fe = pushed(p, top, strains, [8])
    ref, psi = uniaxial_point_driver(mat, strains)
    # the model's UFL stored energy at the committed plastic state = the kernel's psi
    energy = fem.assemble_scalar(fem.form(p.model.stored_energy(p.split(p.w), p.state.committed)
                                          * p.dx, jit_options=p.jit_options))
    assert abs(energy - psi) < 1e-8 * psi
    assert fe[0, 0] > 0 and np.all(np.diff(fe[:, 0]) > 0)
    assert np.all(p.state.owned("equivalent_plastic_strain").reshape(-1, 5)[:, 1:] == 0)
    np.testing.assert_allclose(fe, ref, rtol=1e-8)
    assert max(its) <= 6, its
    print("one element: iterations", its, "eq", fe[:, 0], "P_zz", fe[:, 1],
          "vs the point", np.abs(fe / ref - 1).max())


def plane_strain_point_driver(mat, strains):
    """The material point in plane-strain uniaxial stress by itself: for each u_y,y, the
    u_x,x and in-plane phi (4) that make P_xx = 0 and the in-plane Q = 0, with u_z,z = 0 and
    the out-of-plane phi zero (scipy's hybr, the return's tangent as Jacobian), the plastic
    state committed step by step. Returns (eq macro, P_yy, P_zz) per step."""
    tab = kernel_tables(mat)
    state, v = initial_state(), np.zeros(5)
    out = []
    rows, cols = np.r_[0, 9, 10, 12, 13], np.r_[0, 9, 10, 12, 13]   # P_xx, Q_ab; u_x,x, phi_ab

    def fields(v, eyy):
        phi = np.zeros((3, 3))
        phi[:2, :2] = v[1:].reshape(2, 2)
        return np.diag([v[0], eyy, 0.0]), np.eye(3) + phi, np.zeros((3, 3, 3))

    for eyy in strains:
        def residual(v, eyy=eyy, state=state):
            info = finite_return(*fields(v, eyy), state, mat, tab, tangent=True)[4]
            return info["nominal"][rows] / MU, info["tangent"][np.ix_(rows, cols)] / MU

        sol = scipy.optimize.root(residual, v, jac=True, method="hybr", options={"xtol": 1e-14})
        assert np.abs(residual(sol.x)[0]).max() < 1e-12
        v = sol.x
        _, _, _, state, info = finite_return(*fields(v, eyy), state, mat, tab)
        out.append((state["eq"][0], info["nominal"][4], info["nominal"][8]))
    return np.array(out)


def test_plane_strain_element_equals_the_plane_strain_point():
    """2D plane strain: one bilinear quadrilateral (u, phi of degree 1, 4 points), symmetry
    lines, the top pushed down 12 % in four steps, the side free: every point holds the
    material point's own plane-strain uniaxial state (out-of-plane motion held, the
    out-of-plane stress P_zz it carries included) to 1e-8, with Newton on the consistent
    tangent in a few iterations a step; the in-plane Cauchy stress of the model's stresses
    is the point's."""
    from mpi4py import MPI

    from dolfinx import fem, mesh

    from granfe.models.micromorphic_finite_plastic import MicromorphicFiniteDruckerPrager
    from granfe.problem import ContinuumProblem

    mat = material(c=20e3)
    domain = mesh.create_unit_square(MPI.COMM_SELF, 1, 1, mesh.CellType.quadrilateral)
    p = ContinuumProblem(domain, MicromorphicFiniteDruckerPrager(mat), degree=(1, 1),
                         quadrature_degree=2, prefix="mmfdp_ps_")
    p.fix(lambda x: np.isclose(x[0], 0.0), "u_x")
    p.fix(lambda x: np.isclose(x[1], 0.0), "u_y")
    top = p.fix(lambda x: np.isclose(x[1], 1.0), "u_y", 0.0)
    strains = [-0.02, -0.05, -0.08, -0.12]
    its, fe = pushed(p, top, strains, [4, 8])
    ref = plane_strain_point_driver(mat, strains)
    assert fe[0, 0] > 0 and np.all(np.diff(fe[:, 0]) > 0) and np.all(fe[:, 2] < 0)
    np.testing.assert_allclose(fe, ref, rtol=1e-8)
    assert max(its) <= 6, its
    # sigma = P F^T / J with F = diag(F_xx, F_yy): sigma_yy = P_yy / F_xx, over the unit area
    u = p.w.sub(0).collapse()
    x = u.function_space.tabulate_dof_coordinates()
    u_xx = u.x.array.reshape(-1, 2)[np.argmax(x[:, 0]), 0]      # u_x on the side x = 1
    cauchy = p.model.stresses(p.split(p.w), p.state.committed)["cauchy"]
    sigma_yy = fem.assemble_scalar(fem.form(cauchy[1, 1] * p.dx, jit_options=p.jit_options))
    assert u_xx > 0 and sigma_yy == pytest.approx(ref[-1, 1] / (1 + u_xx), rel=1e-8)


def test_rough_platens_residual_has_a_quadratic_taylor_remainder():
    """Two trilinear hexahedra stacked between rough platens (u_x = u_y = 0 and phi = 0 top
    and bottom; the middle nodes free), past a committed plastic step with every level yielding: the remainder
    |F(w + h dw) - F(w) - h J(w) dw| of the assembled residual (the points evaluated at
    every w) falls as h^2, so the Jacobian is the derivative of the residual."""
    from mpi4py import MPI

    import ufl
    from dolfinx import fem, mesh

    from granfe.models.micromorphic_finite_plastic import MicromorphicFiniteDruckerPrager
    from granfe.problem import ContinuumProblem

    domain = mesh.create_box(MPI.COMM_SELF, [[0, 0, 0], [1, 1, 1]], [1, 1, 2],
                             mesh.CellType.hexahedron)
    mat = material(c=20e3, friction=20.0, dilatancy=5.0)
    p = ContinuumProblem(domain, MicromorphicFiniteDruckerPrager(mat), degree=(1, 1),
                         quadrature_degree=2, prefix="mmfdp_taylor_")
    bottom, top = (lambda x: np.isclose(x[2], 0.0)), (lambda x: np.isclose(x[2], 1.0))
    for where, names in ((bottom, ("u", "phi")), (top, ("u_x", "u_y", "phi"))):
        for name in names:
            p.fix(where, name)
    drive = p.fix(top, "u_z", 0.0)
    drive.value = -0.02
    p.solve()
    drive.value = -0.03
    p.solve(commit=False)
    assert p.state.trial["yielding"].x.array.reshape(-1, 3).max(axis=0).tolist() == [1.0] * 3
    F = p.residual()
    Fc, dw = fem.form(F), fem.Function(p.V)
    dw.x.array[:] = np.random.default_rng(0).standard_normal(dw.x.array.size) * 1e-3
    for bc in p.bcs:
        bc.set(dw.x.array, alpha=0.0)
    Jdw = fem.form(ufl.action(ufl.derivative(F, p.w), dw))
    w0 = p.w.x.array.copy()

    def residual():
        p.w.x.scatter_forward()
        p.model.evaluate_points(p)
        return fem.assemble_vector(Fc).array.copy()

    R0, JdW = residual(), fem.assemble_vector(Jdw).array.copy()
    remainders = []
    for h in (1e-2, 5e-3, 2.5e-3, 1.25e-3):
        p.w.x.array[:] = w0 + h * dw.x.array
        remainders.append(np.linalg.norm(residual() - R0 - h * JdW))
    rates = np.log2(np.array(remainders[:-1]) / remainders[1:])
    assert np.all(rates > 1.8), (remainders, rates)
    print("rough platens: Taylor remainders", remainders, "rates", rates)


def rough_platen_fields(model, strain, prefix):
    """Two trilinear hexahedra between rough platens pushed down by ``strain`` in two
    steps: the fields (u, phi) and the committed equivalent plastic strains."""
    from mpi4py import MPI

    from dolfinx import mesh

    from granfe.problem import ContinuumProblem

    domain = mesh.create_box(MPI.COMM_SELF, [[0, 0, 0], [1, 1, 1]], [1, 1, 2],
                             mesh.CellType.hexahedron)
    p = ContinuumProblem(domain, model, degree=(1, 1), quadrature_degree=2, prefix=prefix)
    bottom, top = (lambda x: np.isclose(x[2], 0.0)), (lambda x: np.isclose(x[2], 1.0))
    for where, names in ((bottom, ("u", "phi")), (top, ("u_x", "u_y", "phi"))):
        for name in names:
            p.fix(where, name)
    drive = p.fix(top, "u_z", 0.0)
    for e in (0.5 * strain, strain):
        drive.value = -e
        p.solve()
    return p.w.x.array.copy(), p.state.owned("equivalent_plastic_strain").reshape(-1, 5)


def test_mesh_small_strain_limit_is_the_small_strain_iterative_model():
    """The same mesh problem (rough platens, coupled moduli; macro, micro and the z slice of
    the higher-order level yielding at every point) with the finite-strain model and with
    the small-strain MicromorphicDruckerPragerIterative at strains 1e-5 and 1e-6: fields and
    equivalent plastic strains differ by O(strain), tenfold less at the smaller strain."""
    from granfe.models.micromorphic_finite_plastic import MicromorphicFiniteDruckerPrager
    from granfe.models.micromorphic_iterative import MicromorphicDruckerPragerIterative

    diffs = []
    for k, size in enumerate((1e-5, 1e-6)):
        mat = material(c=0.02 * MU * size, friction=20.0, dilatancy=5.0, hardening=0.2 * MU)
        w_f, eq_f = rough_platen_fields(MicromorphicFiniteDruckerPrager(mat), size,
                                        f"mmfdp_lim_f{k}_")
        w_s, eq_s = rough_platen_fields(MicromorphicDruckerPragerIterative(mat), size,
                                        f"mmfdp_lim_s{k}_")
        assert np.all(eq_s[:, [0, 1, 4]] > 0)   # macro, micro and the z slice, every point
        diffs.append((np.abs(w_f - w_s).max() / np.abs(w_s).max(),
                      np.abs(eq_f - eq_s).max() / np.abs(eq_s).max()))
    print("mesh small-strain limit (1e-5, 1e-6):", diffs)
    for a, b in zip(*diffs, strict=True):
        assert a < 20e-5 and b < 20e-6 and 5 < a / b < 20, diffs
