"""Load stepping (granfe.stepping): the secant predictor and the load-increment tolerance
follow the same plastic path in fewer Newton iterations; a step that fails is cut back;
bad controls are refused by name."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
from dolfinx import mesh

from granfe.materials import MicropolarMaterial
from granfe.models.drucker_prager import DruckerPragerMaterial, MicropolarDruckerPrager
from granfe.problem import ContinuumProblem
from granfe.solvers import ONE_LU_PER_STEP
from granfe.stepping import LoadStepFailed, StepControl, follow_load_path

ELASTIC = MicropolarMaterial.from_engineering(50e6, 0.3, length=0.02, kappa_over_mu=0.5,
                                              gamma_over_l2mu=1.0)
C = 10e3
SETTLEMENT = 4e-3           # [m]: the punch well past the first yield (~1e-3)


def punch(tag: str, **petsc):
    """A rough rigid punch on half the top of a cohesive-frictional block (1 x 0.5 m, plane
    strain): a plastic zone that grows and, beside it, points that unload."""
    domain = mesh.create_rectangle(MPI.COMM_WORLD, [[0.0, 0.0], [1.0, 0.5]], [16, 8],
                                   mesh.CellType.triangle)
    mat = DruckerPragerMaterial(ELASTIC, C, 25.0, 5.0, match="plane_strain")
    p = ContinuumProblem(domain, MicropolarDruckerPrager(mat), degree=(1, 1),
                         prefix=f"stepping_{tag}_", petsc_options=petsc or None)
    p.fix(lambda x: np.isclose(x[1], 0.0), "u")
    p.fix(lambda x: np.isclose(x[0], 0.0), "u_x")
    p.fix(lambda x: np.isclose(x[0], 1.0), "u_x")

    def under(x):
        return np.isclose(x[1], 0.5) & (x[0] <= 0.5 + 1e-9)

    p.fix(under, "u_x")
    p.fix(under, "phi")
    return p, p.fix(under, "u_y", 0.0), under


def follow(control: StepControl, tag: str, **petsc):
    problem, settle, under = punch(tag, **petsc)
    forces = []
    steps = follow_load_path(problem, lambda t: setattr(settle, "value", -t), SETTLEMENT, control,
                             on_step=lambda t, its: forces.append(-problem.reaction(under, "u_y")))
    return np.array(forces), [its for _, its in steps], problem


def test_secant_predictor_and_load_tolerance_follow_the_same_path_in_fewer_iterations():
    """Eight equal steps: the punch forces of every step agree to 1e-7 of the force (the
    default stops at 1e-10 of each step's first residual, the other at 1e-8 of the load
    increment's residual), in fewer Newton iterations overall; the solver's own tolerances
    are back after the path."""
    base = dict(first=SETTLEMENT / 8, min_step=SETTLEMENT / 64, max_step=SETTLEMENT / 8)
    f_ref, its_ref, _ = follow(StepControl(**base), "default")
    f, its, problem = follow(StepControl(**base, predictor="secant", load_tol=1e-8), "secant")
    assert len(f) == len(f_ref) == 8
    np.testing.assert_allclose(f, f_ref, rtol=1e-7)
    assert problem.state.owned("yielding").any()           # the path is plastic
    assert sum(its) < sum(its_ref), (its, its_ref)
    rtol, atol = problem.snes.getTolerances()[:2]
    assert (rtol, atol) == (1e-10, 1e-14), "the solver's tolerances are restored after each step"
    # one LU a step preconditioning GMRES: the same Newton iterates
    f_lu, its_lu, problem = follow(StepControl(**base, predictor="secant", load_tol=1e-8), "one_lu",
                                   **ONE_LU_PER_STEP)
    np.testing.assert_allclose(f_lu, f_ref, rtol=1e-7)
    assert problem.snes.getKSP().getType() == "gmres"


def test_a_failing_step_is_cut_back_and_a_step_below_min_step_gives_up():
    """With Newton allowed 5 iterations (a step of an eighth of the path takes 4-5), the large
    steps fail and are halved until they pass; with min_step at the first step, the first
    failure ends the path (the last converged state kept)."""
    problem, settle, under = punch("cutback", snes_max_it=5)
    logged = []
    steps = follow_load_path(problem, lambda t: setattr(settle, "value", -t), SETTLEMENT,
                             StepControl(first=SETTLEMENT / 2, min_step=SETTLEMENT / 256,
                                         max_step=SETTLEMENT / 2), log=logged.append)
    assert logged and all("cut back" in m for m in logged)
    t = np.array([0.0] + [t for t, _ in steps])
    assert np.diff(t).min() < SETTLEMENT / 2
    assert steps[-1][0] == pytest.approx(SETTLEMENT)
    problem, settle, under = punch("giveup", snes_max_it=5)
    with pytest.raises(LoadStepFailed, match="min_step"):
        follow_load_path(problem, lambda t: setattr(settle, "value", -t), SETTLEMENT,
                         StepControl(first=SETTLEMENT / 2, min_step=SETTLEMENT / 2, max_step=SETTLEMENT))
    assert np.isfinite(problem.w.x.array).all()


@pytest.mark.parametrize("kwargs, key", [
    (dict(predictor="linear"), "predictor"),
    (dict(load_tol=0.0), "load_tol"),
    (dict(load_tol=float("nan")), "load_tol"),
    (dict(min_step=2.0), "min_step"),
])
def test_step_control_is_validated(kwargs, key):
    with pytest.raises(ValueError, match=key):
        StepControl(**{**dict(first=1.0, min_step=0.1, max_step=1.0), **kwargs})
