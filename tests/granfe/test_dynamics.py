"""Generalized-alpha dynamics: exact energy conservation at rho_inf = 1, dissipation below,
second-order accuracy in time."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
from dolfinx import mesh

from granfe.dynamics import AlphaParameters, GeneralizedAlpha
from granfe.materials import MicropolarMaterial
from granfe.problem import MicropolarProblem

MAT = MicropolarMaterial.from_engineering(1.0e9, 0.3, length=0.05, kappa_over_mu=0.5, rho=2000.0)


def vibrating_bar(rho_inf, dt, prefix):
    """A clamped bar released from a uniform initial velocity field (u = 0, so a_0 = 0 is consistent)."""
    domain = mesh.create_rectangle(MPI.COMM_WORLD, [[0, 0], [1, 0.2]], [10, 2])
    problem = MicropolarProblem(domain, MAT, prefix=prefix)
    clamp = lambda x: np.isclose(x[0], 0.0)  # noqa: E731
    problem.fix(clamp, "u")
    problem.fix(clamp, "phi")
    stepper = GeneralizedAlpha(problem, dt, rho_inf=rho_inf)
    stepper.v.sub(0).interpolate(lambda x: np.vstack([0.0 * x[0], 0.01 * x[0] ** 2]))
    stepper.v.sub(1).interpolate(lambda x: 0.02 * x[0])
    return stepper


def test_energy_conserved_over_1000_steps():
    stepper = vibrating_bar(1.0, 2e-5, "energy_")
    E0 = sum(stepper.energies())
    drift = []
    for _ in range(1000):
        stepper.step()
        drift.append(abs(sum(stepper.energies()) - E0) / E0)
    kinetic, elastic = stepper.energies()
    assert elastic > 0.1 * E0  # the bar really vibrates: energy moves between the two
    assert max(drift) < 1e-8


def test_rho_inf_below_one_dissipates():
    stepper = vibrating_bar(0.0, 2e-4, "dissip_")  # steps longer than the high-mode periods
    energies = [sum(stepper.energies())]
    for _ in range(200):
        stepper.step()
        energies.append(sum(stepper.energies()))
    assert energies[-1] < 0.98 * energies[0]


def test_second_order_in_time():
    """Tip displacement at t = 2 ms against a 4x finer step: error ratio 4 on halving dt."""
    T = 2e-3
    tips = {}
    for n in (20, 40, 160):
        stepper = vibrating_bar(0.8, T / n, f"order{n}_")
        for _ in range(n):
            stepper.step()
        tips[n] = stepper.problem.w.x.array.copy()
    e1 = np.linalg.norm(tips[20] - tips[160])
    e2 = np.linalg.norm(tips[40] - tips[160])
    e1, e2 = (MPI.COMM_WORLD.allreduce(e**2, MPI.SUM) ** 0.5 for e in (e1, e2))
    assert np.log2(e1 / e2) > 1.8


def test_bad_parameters_named():
    with pytest.raises(ValueError, match="rho_inf"):
        AlphaParameters(1.5)
    stepper_problem = vibrating_bar(1.0, 1e-5, "bad_").problem
    with pytest.raises(ValueError, match="dt"):
        GeneralizedAlpha(stepper_problem, -1.0)
    with pytest.raises(ValueError, match="tangent must be 'elastic' or 'consistent'"):
        GeneralizedAlpha(stepper_problem, 1e-5, tangent="secant")


def test_consistent_initial_acceleration():
    """a_0 from M a_0 = -K u_0 makes the first step match a step from the exact state."""
    stepper = vibrating_bar(1.0, 1e-5, "acc0_")
    stepper.problem.w.sub(0).interpolate(lambda x: np.vstack([1e-6 * x[0], 2e-6 * x[0] ** 2]))
    stepper.initialize_acceleration()
    # M a + K u = 0 tested against the assembled residual of the first-step equation at dt -> 0
    import ufl
    from dolfinx import fem

    from granfe.forms import inertia_work, internal_work
    p = stepper.problem
    u, phi = ufl.split(p.w)
    au, aphi = ufl.split(stepper.a)
    du, dphi = ufl.TestFunctions(p.V)
    F = fem.form((inertia_work(au, aphi, du, dphi, p.constants)
                  + internal_work(u, phi, du, dphi, p.constants)) * p.dx)
    r = fem.assemble_vector(F)
    fixed = np.concatenate([bc.dof_indices()[0] for bc in p.bcs])
    r.array[fixed] = 0.0
    internal = fem.form(internal_work(u, phi, du, dphi, p.constants) * p.dx)
    scale = np.abs(fem.assemble_vector(internal).array).max()
    assert np.abs(r.array).max() < 1e-10 * scale


@pytest.mark.mpi
def test_affine_step_equals_newton():
    """The linear step (Jacobian factorised once, by Cholesky: it is symmetric; residual by
    matrix products) gives the SNES solve's states (LU, the Jacobian assembled every
    iteration) to round-off, with Dirichlet values and a load that change every step and a
    change of dt (re-assembled and refactorised) half way."""
    from dolfinx import fem

    states = []
    for affine in (True, False):
        domain = mesh.create_rectangle(MPI.COMM_WORLD, [[0, 0], [1, 0.2]], [10, 2])
        # the reference: Newton with the Jacobian assembled at every iteration
        problem = MicropolarProblem(domain, MAT, prefix=f"affine{int(affine)}_",
                                    petsc_options={} if affine else {"snes_lag_jacobian": 1})
        clamp = lambda x: np.isclose(x[0], 0.0)  # noqa: E731
        problem.fix(clamp, "phi")
        pull = problem.fix(clamp, "u_x", fem.Constant(domain, 0.0))
        load = problem.body_force((0.0, 0.0))
        stepper = GeneralizedAlpha(problem, 2e-5, rho_inf=0.8, prefix=f"affine_dyn{int(affine)}_")
        assert stepper._affine is not None
        if not affine:
            stepper._affine = None   # the SNES (Newton) path
        history = []
        for k in range(30):
            if k == 15:
                stepper.dt.value = 1e-5
            pull.value = 1e-6 * np.sin(0.3 * k)
            load.value = (0.0, -2e4 * (1 + np.cos(0.2 * k)))
            stepper.step()
            history.append(np.concatenate([problem.w.x.array, stepper.v.x.array, stepper.a.x.array]))
        if affine:
            assert stepper._affine.factorisation == "cholesky"
        states.append(np.array(history))
    a, b = states
    scale = np.abs(b).max(axis=1, keepdims=True)
    assert np.all(np.abs(a - b) <= 1e-10 * scale)
    assert np.abs(b[:, : len(b[0]) // 3]).max() > 0   # the bar moved
