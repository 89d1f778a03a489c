"""The mechanics' step of a staggered Biot split (`granfe.models.undrained_split`), with a P1
Darcy step after each FE step written here in plain UFL (as a coupling solves its fluid):
Terzaghi's consolidation against the closed form, a strip load in 2D that stays bounded in
the undrained limit, and bad input.

Tolerances: the split is first order in time (the flow takes the step's volume change, then
the mechanics the flow's pressure), but the model's step holds the continuum's own flow, so
the split's error is the flow's backward Euler: at 200 steps to T = 1 the settlement within
0.44 % and the undrained base's pressure within 0.52 % of the closed forms (asserted 1 %;
without the flow in the step, the undrained split proper, -20 % at T = 0.1 and -4 % at
T = 1, first order). The strip load: a pressure increment of the cell's own divergence
instead of the model's P1 field grew from 1 kPa to 1e13 Pa in 100 steps at the same step
(the flow's undrained answer and the mechanics' differed); with the field the pressure
peaks at 2.1 x the load under the strip's edge and falls from there."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
import ufl
from dolfinx import default_scalar_type, fem, mesh
from dolfinx.fem.petsc import LinearProblem

from granfe.consolidation import terzaghi_p0, terzaghi_pressure, terzaghi_settlement
from granfe.dynamics import AlphaParameters, GeneralizedAlpha
from granfe.materials import MicropolarMaterial
from granfe.models.micropolar import Micropolar
from granfe.models.poroelastic import PoreFluid, PoroelasticMaterial
from granfe.models.undrained_split import UndrainedSplit
from granfe.probe import probe
from granfe.problem import ContinuumProblem

LAM, MU = 4e4, 3e4              # a loose sand's skeleton [Pa]
STORAGE = 0.4 * 1e-6            # n beta_f [1/Pa]: Skempton's B ~ 0.96
MOBILITY = 3e-12 / 1e-3         # k / mu_f [m^2 / (Pa s)]
Q = 1e3                         # load [Pa]
SOIL = PoroelasticMaterial(LAM, MU, PoreFluid(k=3e-12, mu_f=1e-3, alpha=1.0, M=1.0 / STORAGE))


def split_run(domain, loaded, steps: int, dt: float, every=None, flow_in_step=True):
    """The split on ``domain`` under a load Q on the top facets ``loaded`` (x -> bool), drained
    at the top, rollers on the sides and the bottom: ``steps`` FE steps of ``dt``, each
    followed by a backward-Euler Darcy step with the FE step's displacement change as its
    source. Yields (step, problem, pressure) after each flow step (every ``every``)."""
    W, H = domain.geometry.x[:, 0].max(), domain.geometry.x[:, 1].max()
    # nearly no inertia: the quasi-static limit the closed forms have
    material = MicropolarMaterial(lam=LAM, mu=MU, kappa=1.0, gamma=1e-6, rho=1e-6, j=1e-6)
    model = UndrainedSplit(Micropolar(material), storage=STORAGE, mobility=MOBILITY if flow_in_step else 0.0)
    problem = ContinuumProblem(domain, model, degree=(1, 1, 1), prefix=f"split{id(domain)}_")
    problem.fix(lambda x: np.isclose(x[1], 0), "u_y")
    problem.fix(lambda x: np.isclose(x[0], 0) | np.isclose(x[0], W), "u_x")
    problem.fix(lambda x: np.isclose(x[1], H), "p")
    problem.traction(lambda x: np.isclose(x[1], H) & loaded(x), (0.0, -Q))
    V1 = fem.functionspace(domain, ("Lagrange", 1))
    p_flow, w_start = fem.Function(V1), fem.Function(problem.V)
    u_start = problem.split(w_start)[0]
    problem.volume_work(lambda dw: p_flow * ufl.div(dw[0]) - ufl.div(u_start) * dw[-1]
                        + model.step * model.mobility * ufl.inner(ufl.grad(p_flow), ufl.grad(dw[-1])))
    model.step.value = (1 - AlphaParameters(0.8).alpha_f) * dt   # (the mid-point is (1 - alpha_f) dt in)
    stepper = GeneralizedAlpha(problem, dt, rho_inf=0.8)
    # the flow: S (p - p_n) / dt - div(k / mu grad p) = -div v, v the step's displacement rate
    Vv = fem.functionspace(domain, ("Lagrange", 1, (2,)))
    rate, v, p_old = fem.Function(problem.V), fem.Function(Vv), fem.Function(V1)
    p, q = ufl.TrialFunction(V1), ufl.TestFunction(V1)
    a = STORAGE / dt * p * q * ufl.dx + MOBILITY * ufl.inner(ufl.grad(p), ufl.grad(q)) * ufl.dx
    L = STORAGE / dt * p_old * q * ufl.dx + ufl.inner(v, ufl.grad(q)) * ufl.dx
    top = fem.locate_dofs_geometrical(V1, lambda x: np.isclose(x[1], H))
    flow = LinearProblem(a, L, bcs=[fem.dirichletbc(default_scalar_type(0), top, V1)], u=p_flow,
                         petsc_options_prefix=f"split_flow{id(domain)}_",
                         petsc_options={"ksp_type": "preonly", "pc_type": "lu"})
    for k in range(steps):
        stepper.step()
        rate.x.array[:] = (problem.w.x.array - w_start.x.array) / dt
        v.interpolate(rate.sub(0))
        p_old.x.array[:] = p_flow.x.array
        flow.solve()
        w_start.x.array[:] = problem.w.x.array
        if every is None or (k + 1) % every == 0:
            yield k + 1, problem, p_flow


def test_terzaghi_consolidation_by_the_split():
    H = 1.0
    domain = mesh.create_rectangle(MPI.COMM_WORLD, [[0, 0], [0.1, H]], [1, 40])
    c = SOIL.c_oedometric
    tc = H**2 / c
    steps, T = 200, 1.0
    dt = T * tc / steps
    errors = []
    for k, problem, p in split_run(domain, lambda x: np.full(x.shape[1], True), steps, dt, every=20):
        t = k * dt
        settlement = -probe(problem.w.sub(0).collapse(), np.array([[0.05, H, 0.0]]))[0, 1]
        exact = terzaghi_settlement(t, H=H, q=Q, material=SOIL)
        base = probe(p, np.array([[0.05, 0.0, 0.0]]))[0, 0]   # (the undrained base)
        p_exact = terzaghi_pressure(H, t, H=H, p0=terzaghi_p0(Q, SOIL), c=c)
        errors.append((t / tc, settlement / exact - 1, (base - p_exact) / terzaghi_p0(Q, SOIL)))
    assert len(errors) == 10
    for T_, e, e_p in errors:   # measured: settlement 0.44 % at most, base pressure 0.52 %
        assert abs(e) < 0.01 and abs(e_p) < 0.01, (T_, e, e_p)


def test_a_strip_load_stays_bounded_undrained():
    """A strip on half the top of a square, at steps of 1e-5 of its consolidation time:
    nearly undrained, the pressure under the strip near the load (Skempton's B times the
    strip's stress), not a growing mode."""
    domain = mesh.create_rectangle(MPI.COMM_WORLD, [[0, 0], [0.1, 0.1]], [20, 20],
                                   diagonal=mesh.DiagonalType.crossed)
    dt = 1e-5 * 0.1**2 / (MOBILITY * (LAM + 2 * MU)) / 100
    peaks = [MPI.COMM_WORLD.allreduce(float(np.abs(p.x.array).max()), op=MPI.MAX)
             for _, _, p in split_run(domain, lambda x: x[0] < 0.05 + 1e-9, 100, dt, every=10)]
    # measured 2.08 Q after 10 steps, falling steadily to 1.65 Q after 100
    assert max(peaks) < 2.5 * Q
    assert 0.5 * Q < peaks[-1] < peaks[0]


def test_the_step_is_factorised_once_and_follows_its_share():
    """The split's step is linear with a fixed share field (`ContinuumModel.fixed_fields`):
    the generalized-alpha step solves it with one factorisation (`_AffineStep`; Cholesky:
    MUMPS's symmetric indefinite LDL^T) as Newton does (SNES, LU, its Jacobian assembled
    every iteration) to 1e-10 (measured 1e-14), also after the share changes between steps
    (the factors renewed)."""
    domain = mesh.create_rectangle(MPI.COMM_WORLD, [[0, 0], [0.1, 0.1]], [6, 6])
    runs = []
    for affine in (True, False):
        material = MicropolarMaterial(lam=LAM, mu=MU, kappa=1.0, gamma=1e-6, rho=2e3, j=1e-6)
        model = UndrainedSplit(Micropolar(material), storage=STORAGE, mobility=MOBILITY)
        problem = ContinuumProblem(domain, model, degree=(1, 1, 1), prefix=f"split_once{int(affine)}_",
                                   petsc_options={} if affine else {"snes_lag_jacobian": 1})
        problem.fix(lambda x: np.isclose(x[1], 0), "u_y")
        problem.fix(lambda x: np.isclose(x[0], 0), "u_x")
        problem.fix(lambda x: np.isclose(x[1], 0.1), "p")
        problem.traction(lambda x: np.isclose(x[1], 0.1), (0.0, -Q))
        model.step.value = 1e-4
        stepper = GeneralizedAlpha(problem, 1e-4, rho_inf=0.8, prefix=f"split_once_dyn{int(affine)}_")
        assert stepper._affine is not None
        if not affine:
            stepper._affine = None     # (the SNES path)
        history = []
        for k in range(12):
            if k == 6:   # (a share changed between steps: half the skeleton's)
                model.share.x.array[:] = np.where(model.share.function_space.tabulate_dof_coordinates()[:, 0]
                                                  < 0.05, 0.5, 1.0)
            stepper.step()
            history.append(problem.w.x.array.copy())
        assert not affine or stepper._affine.factorisation == "cholesky"
        runs.append(np.array(history))
    scale = np.abs(runs[1]).max()
    assert scale > 0
    np.testing.assert_allclose(runs[0], runs[1], atol=1e-10 * scale)


def test_bad_input_is_named():
    material = MicropolarMaterial(lam=LAM, mu=MU, kappa=1e3, gamma=1e-6, rho=1.0, j=1e-6)
    with pytest.raises(ValueError, match="storage must be a positive number"):
        UndrainedSplit(Micropolar(material), storage=0.0)
    with pytest.raises(ValueError, match="storage must be a positive number"):
        UndrainedSplit(Micropolar(material), storage=float("nan"))
    from granfe.models.drucker_prager import DruckerPragerMaterial, MicropolarDruckerPrager

    plastic = MicropolarDruckerPrager(DruckerPragerMaterial(material, 1e3, 30.0, 0.0))
    with pytest.raises(ValueError, match="the skeleton must be linear"):
        UndrainedSplit(plastic, storage=STORAGE)
