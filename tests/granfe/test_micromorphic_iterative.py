"""Micromorphic Drucker-Prager with the return at the quadrature points (any moduli):
decoupled moduli give the closed-form radial returns (at a point, and the closed-form model
on a mesh, quasi-static and explicit); with coupled moduli the associated return is the
closest point in the energy norm (an independent constrained minimisation), the tangent is
the derivative of the return (finite differences, and Newton's Taylor remainder on a mesh),
checkpoints continue exactly, serial = 2 ranks, and generalized-alpha steps (the return at its
mid-point fields) equal the closed-form model's."""

import sys
from dataclasses import replace
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
import scipy.optimize
import ufl
from dolfinx import fem, mesh

sys.path.insert(0, str(Path(__file__).parent))
from test_micromorphic_plasticity import ELASTIC, LENGTH, MU, _at, block, material  # noqa: E402

from granfe.models.micromorphic_drucker_prager import Cone, MicromorphicDruckerPrager  # noqa: E402
from granfe.models.micromorphic_iterative import MicromorphicDruckerPragerIterative  # noqa: E402
from granfe.models.micromorphic_return import level_moduli, point_return, stiffness  # noqa: E402
from granfe.problem import ContinuumProblem  # noqa: E402

C = 10e3
L2 = MU * LENGTH**2
COUPLED = replace(ELASTIC, tau=2e6, sigma=1.5e6, tau1=0.1 * L2, tau2=0.05 * L2, tau4=0.1 * L2,
                  tau8=0.05 * L2, tau11=0.02 * L2)


def cones_table(friction=30.0, dilatancy=10.0, hardening=2e6):
    rows = [Cone(C, friction, dilatancy, hardening)] * 2 + [
        Cone(C * LENGTH, friction, dilatancy, hardening * LENGTH**2)] * 3
    return np.array([[*c.constants, c.hardening] for c in rows])


def random_measures(n, seed, size=1e-3):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 45)) * size
    eps = x[:, :9].reshape(n, 3, 3)
    x[:, :9] = ((eps + eps.transpose(0, 2, 1)) / 2).reshape(n, 9)
    x[:, 18:] /= LENGTH
    return x


def radial_return(t, G, Kv, A, B, k0, H, eq):
    """Classical Drucker-Prager radial return with the apex (numpy), one level."""
    p = np.trace(t) / 3
    dev = t - p * np.eye(3)
    tau = np.sqrt(0.5 * np.sum(dev * dev))
    k = k0 + H * eq
    f = tau + A * p - k
    if f <= 0:
        return t
    dl = f / (G + Kv * A * B + H)
    if tau - G * dl >= 0:
        return (1 - G * dl / tau) * dev + (p - Kv * B * dl) * np.eye(3)
    stiff = Kv * A * B + H
    if stiff > 0:
        return (p - Kv * B * (A * p - k) / stiff) * np.eye(3)
    return k / A * np.eye(3)


def level_stress(y, i):
    t = y[9 * i: 9 * i + 9].reshape(3, 3)
    return (t + t.T) / 2 if i < 2 else t


def test_decoupled_point_return_is_the_radial_return():
    """Decoupled levels with hardening and a committed plastic state: every level's stress
    is its own radial return (cone or apex) to round-off."""
    K, cones = stiffness(ELASTIC), cones_table()
    x = random_measures(150, 0)
    rng = np.random.default_rng(1)
    xp_old = random_measures(150, 2, size=2e-4)
    eq_old = rng.uniform(0, 0.01, size=(150, 5))
    y, _, _, eq, flags, failed = point_return(x, xp_old, eq_old, K, cones, np.ones(5, bool))
    assert failed == 0 and 0.5 < flags.mean() < 1.0
    moduli = level_moduli(K)
    y_trial = (x - xp_old) @ K.T
    apexes = 0
    for n in range(len(x)):
        for i in range(5):
            ref = radial_return(level_stress(y_trial[n], i), *moduli[i], *cones[i], eq_old[n, i])
            np.testing.assert_allclose(level_stress(y[n], i), ref, rtol=0,
                                       atol=1e-11 * np.abs(y_trial[n]).max())
            apexes += flags[n, i] and np.allclose(ref, np.trace(ref) / 3 * np.eye(3))
    assert apexes > 0                                  # some points return to the apex
    assert np.all(eq >= eq_old)


def test_coupled_tangent_is_the_derivative_of_the_return():
    """Coupled moduli, non-associated, hardening: the consistent tangent equals central
    differences of the returned stress."""
    K, cones = stiffness(COUPLED), cones_table()
    x = random_measures(6, 3)
    zeros = (np.zeros((1, 45)), np.zeros((1, 5)))
    for n in range(len(x)):
        y, C_n, _, _, flags, failed = point_return(x[n: n + 1], *zeros, K, cones, np.ones(5, bool))
        assert failed == 0 and flags.sum() >= 3
        fd = np.zeros((45, 45))
        for c in range(45):
            h = 1e-7 * max(1.0, abs(x[n, c]))
            up, down = x[n: n + 1].copy(), x[n: n + 1].copy()
            up[0, c] += h
            down[0, c] -= h
            fd[:, c] = (point_return(up, *zeros, K, cones, np.ones(5, bool))[0]
                        - point_return(down, *zeros, K, cones, np.ones(5, bool))[0])[0] / (2 * h)
        # the return converges to ~1e-9 of the stress (the Newton's round-off floor with
        # coupled levels), which the differences divide by h: 1e-5 of the largest modulus
        # (a tangent missing a level's coupling is off by order one)
        assert np.abs(fd - C_n[0]).max() < 1e-4 * np.abs(C_n[0]).max()


def test_coupled_associated_return_is_the_closest_point():
    """Associated, perfectly plastic, coupled moduli: the returned stress is admissible and
    no admissible stress is closer to the trial one in the complementary energy norm
    (SLSQP from the trial stress and from the return find nothing closer)."""
    K, cones = stiffness(COUPLED), cones_table(friction=30.0, dilatancy=30.0, hardening=0.0)
    x = random_measures(5, 4)
    y, *_, flags, failed = point_return(x, np.zeros((5, 45)), np.zeros((5, 5)), K, cones,
                                        np.ones(5, bool))
    assert failed == 0 and flags.sum() >= 15
    K_inv = np.linalg.pinv(K)

    def yield_values(v):
        out = []
        for i in range(5):
            t = level_stress(v, i)
            p = np.trace(t) / 3
            dev = t - p * np.eye(3)
            out.append(np.sqrt(0.5 * np.sum(dev * dev)) + cones[i, 0] * p - cones[i, 2])
        return np.array(out)

    for n in range(len(x)):
        trial = K @ x[n]
        s = np.abs(trial).max()
        assert yield_values(y[n]).max() < 1e-10 * s

        def distance(v, trial=trial, s=s):
            return (v - trial) @ K_inv @ (v - trial) / s**2 * 1e6

        ours = distance(y[n])
        for start in (trial, y[n]):
            best = scipy.optimize.minimize(
                distance, start, method="SLSQP", options={"ftol": 1e-16, "maxiter": 500},
                constraints=[{"type": "ineq", "fun": lambda v, s=s: -yield_values(v) / s}])
            if yield_values(best.x).max() < 1e-9 * s:
                assert ours <= best.fun * (1 + 1e-8), (n, ours, best.fun)


def run_block(model, comm=MPI.COMM_WORLD, n=3, steps=(0.004, 0.008, 0.012), prefix="mmi"):
    p, drive = block(model, comm, n=n, prefix=prefix)
    its = []
    for delta in steps:
        drive(delta)
        its.append(p.solve())
    return p, drive, its


def test_decoupled_mesh_run_equals_the_closed_form_model():
    """The loaded plane-strain block over three plastic steps: the same fields and
    equivalent plastic strains as the closed-form (UFL) model."""
    runs = [run_block(cls(material(hardening=2e6)), prefix=f"mmi_eq{k}_")[0]
            for k, cls in enumerate((MicromorphicDruckerPrager, MicromorphicDruckerPragerIterative))]
    a, b = (r.w.x.array for r in runs)
    assert np.abs(a - b).max() < 1e-9 * np.abs(a).max()
    ea, eb = (r.state.owned("equivalent_plastic_strain") for r in runs)
    assert ea.max() > 0 and np.abs(ea - eb).max() < 1e-8 * ea.max()
    np.testing.assert_array_equal(*(r.state.owned("yielding") for r in runs))


def coupled_material(hardening=2e6):
    return replace(material(hardening=hardening), elastic=COUPLED)


def _taylor_remainders(p, steps=(1e-2, 5e-3, 2.5e-3, 1.25e-3)):
    """|F(w + h dw) - F(w) - h J(w) dw|, every residual after the points are evaluated at its
    fields (the model's residual is its linearisation about the last evaluation)."""
    F = p.residual()
    J = ufl.derivative(F, p.w)
    dw = fem.Function(p.V)
    dw.x.array[:] = np.random.default_rng(0).standard_normal(dw.x.array.size) * 1e-4
    for bc in p.bcs:                                  # keep the prescribed values
        bc.set(dw.x.array, alpha=0.0)
    Fc, Jdw = fem.form(F), fem.form(ufl.action(J, dw))
    w0 = p.w.x.array.copy()

    def residual():
        p.w.x.scatter_forward()
        p.model.evaluate_points(p)
        return fem.assemble_vector(Fc).array.copy()

    R0 = residual()
    JdW = fem.assemble_vector(Jdw).array.copy()
    out = []
    for h in steps:
        p.w.x.array[:] = w0 + h * dw.x.array
        out.append(np.linalg.norm(residual() - R0 - h * JdW))
    p.w.x.array[:] = w0
    residual()
    return np.array(out)


def test_coupled_block_converges_quadratically():
    """Coupled moduli, hardening, all three levels yielding: the Taylor remainder of the
    residual falls as h^2 about a trial state past the committed one, and Newton takes as
    few iterations as on the decoupled block."""
    p, drive, its = run_block(MicromorphicDruckerPragerIterative(coupled_material()), prefix="mmi_tay_")
    drive(0.014)
    p.solve(commit=False)
    assert p.state.trial["yielding"].x.array.reshape(-1, 3).max(axis=0).tolist() == [1.0, 1.0, 1.0]
    r = _taylor_remainders(p)
    rates = np.log2(r[:-1] / r[1:])
    assert np.all(rates > 1.8), (r, rates)
    assert max(its) <= 8, its


def test_checkpoint_continues_exactly():
    model = MicromorphicDruckerPragerIterative(coupled_material())
    p, drive, _ = run_block(model, steps=(0.005, 0.01), prefix="mmi_ck_")
    saved = p.state_dict()
    q, drive_q = block(MicromorphicDruckerPragerIterative(coupled_material()), MPI.COMM_WORLD, n=3,
                       prefix="mmi_ck2_")
    q.load_state(saved)
    for problem, d in ((p, drive), (q, drive_q)):
        d(0.013)
        problem.solve()
    np.testing.assert_allclose(q.w.x.array, p.w.x.array, rtol=0, atol=1e-12 * np.abs(p.w.x.array).max())
    np.testing.assert_array_equal(q.state.owned("plastic_micro_strain"), p.state.owned("plastic_micro_strain"))


def test_hydrostatic_tension_returns_to_the_apex_with_coupled_moduli():
    """A unit cube pulled apart equally (u = e x, phi = 0 everywhere): the macro level at its
    apex, A p = k0 with p the mean of S (the coupled micro level loads it too)."""
    mat = replace(material(micro=None, gradient=None), elastic=COUPLED,
                  macro=Cone(C, 30.0, 10.0))
    p = ContinuumProblem(mesh.create_unit_cube(MPI.COMM_WORLD, 1, 1, 1),
                         MicromorphicDruckerPragerIterative(mat), prefix="mmi_apex_")
    p.fix(lambda x: np.full(x.shape[1], True), "u", lambda x: 0.01 * x)
    p.fix(lambda x: np.full(x.shape[1], True), "phi")
    p.solve()
    A, _, k0 = mat.macro.constants
    S = p.state.owned("stress").reshape(-1, 45)[:, :9].reshape(-1, 3, 3)
    np.testing.assert_allclose(np.trace(S, axis1=1, axis2=2) / 3, k0 / A, rtol=1e-10)
    dev = S - np.trace(S, axis1=1, axis2=2)[:, None, None] / 3 * np.eye(3)
    assert np.abs(dev).max() < 1e-8 * k0
    assert p.state.owned("yielding").reshape(-1, 3)[:, 0].min() == 1.0


def stepped(p, drive, stepper, steps, increment):
    """(fields after each step (steps, n), committed equivalent plastic strains) of a
    dynamic stepper driving the block by ``increment`` a step."""
    history = []
    for step in range(1, steps + 1):
        drive(increment * step)
        stepper.step()
        history.append(p.w.x.array.copy())
    return np.array(history), p.state.owned("equivalent_plastic_strain")


def test_explicit_steps_equal_the_closed_form_model():
    """Central differences on a decoupled block of degree-1 fields (the return once a step,
    no solve): the same fields as the closed-form model, step by step."""
    from granfe.explicit import CentralDifference

    runs = []
    for k, cls in enumerate((MicromorphicDruckerPrager, MicromorphicDruckerPragerIterative)):
        p = ContinuumProblem(mesh.create_unit_square(MPI.COMM_WORLD, 2, 2),
                             cls(material(hardening=2e6)), degree=(1, 1), prefix=f"mmi_ex{k}_")
        p.fix(_at(1, 0.0), "u")
        p.fix(_at(1, 0.0), "phi")
        top = (p.fix(_at(1, 1.0), "u_x"), p.fix(_at(1, 1.0), "u_y"))

        def drive(delta, top=top):
            top[0].value, top[1].value = delta, -delta / 2

        runs.append(stepped(p, drive, CentralDifference(p, 2e-6), 8, 0.002))
    assert runs[0][1].max() > 0
    assert np.abs(runs[0][0] - runs[1][0]).max() < 1e-9 * np.abs(runs[0][0]).max()


@pytest.mark.parametrize("tangent", ["elastic", "consistent"])
def test_generalized_alpha_steps_equal_the_closed_form_model(tangent):
    """Generalized-alpha on the decoupled block (the return at the mid-point fields, the
    state committed at the end fields): the same fields and plastic strains as the
    closed-form model step by step, by quasi-Newton on the elastic Jacobian and by Newton."""
    from granfe.dynamics import GeneralizedAlpha

    runs = []
    for k, cls in enumerate((MicromorphicDruckerPrager, MicromorphicDruckerPragerIterative)):
        p, drive = block(cls(material(hardening=2e6)), MPI.COMM_WORLD, n=2, prefix=f"mmi_ga{k}{tangent}_")
        p.petsc_options.update({"snes_rtol": 1e-12, "snes_atol": 1e-12})
        runs.append(stepped(p, drive, GeneralizedAlpha(p, 1e-3, rho_inf=0.8, tangent=tangent), 5, 0.003))
    (wa, ea), (wb, eb) = runs
    assert ea.max() > 0
    assert np.abs(wa - wb).max() < 1e-9 * np.abs(wa).max()
    assert np.abs(ea - eb).max() < 1e-8 * ea.max()


@pytest.mark.mpi
def test_serial_equals_parallel():
    world = run_block(MicromorphicDruckerPragerIterative(coupled_material()), MPI.COMM_WORLD, n=4,
                      prefix="mmi_w_")[0]
    alone = run_block(MicromorphicDruckerPragerIterative(coupled_material()), MPI.COMM_SELF, n=4,
                      prefix="mmi_s_")[0]
    bottom = _at(1, 0.0)
    assert world.reaction(bottom, "u") == pytest.approx(alone.reaction(bottom, "u"), rel=1e-9)
    eq = world.state.committed["equivalent_plastic_strain"].x.array
    assert world.domain.comm.allreduce(eq.max(), MPI.MAX) > 0
