"""The quadrature_stress model (stress and tangent filled at the points): filled with an
elasticity tensor at zero strain it is linear elasticity (against the strain_memory model
without softening, an independent route), 2D plane strain and 3D; filled with a stress
evaluated at the solution's strain, the residual is that of the filled stress alone."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
from dolfinx import fem, mesh

from granfe.models import MODELS
from granfe.models.quadrature_stress import (
    QuadratureStress,
    QuadratureStressMaterial,
    elastic_tangent,
    fill,
)
from granfe.models.strain_memory import StrainMemory, StrainMemoryMaterial
from granfe.problem import ContinuumProblem

LAM, MU = 2.0e8, 1.0e8


def domain(comm, gdim):
    if gdim == 2:
        return mesh.create_rectangle(comm, [[0, 0], [1, 0.5]], [6, 3])
    return mesh.create_box(comm, [[0, 0, 0], [1, 0.5, 0.5]], [4, 2, 2])


def cantilever(model, gdim, prefix, comm=MPI.COMM_WORLD):
    p = ContinuumProblem(domain(comm, gdim), model, prefix=prefix, quadrature_degree=2)
    p.fix(lambda x: np.isclose(x[0], 0.0), "u")
    p.traction(lambda x: np.isclose(x[0], 1.0), (1e5, -2e5, 5e4)[:gdim])
    return p


def filled_elastic(gdim, prefix):
    p = cantilever(QuadratureStress(QuadratureStressMaterial()), gdim, prefix)
    c = elastic_tangent(LAM, MU, gdim)
    n = len(p.state.owned("stress")) // c.shape[0]
    fill(p.state, "tangent", np.broadcast_to(c, (n, *c.shape)))
    return p


def test_registered():
    assert MODELS["quadrature_stress"] is QuadratureStress


@pytest.mark.mpi
@pytest.mark.parametrize("gdim", [2, 3])
def test_filled_elasticity_is_linear_elasticity(gdim):
    q = filled_elastic(gdim, f"qs_el{gdim}_")
    its = q.solve()
    ref = cantilever(StrainMemory(StrainMemoryMaterial(LAM, MU)), gdim, f"qs_ref{gdim}_")
    ref.solve()
    a, b = q.w.x.array, ref.w.x.array
    assert its <= 2  # linear: one Newton step (and the check)
    assert np.abs(a - b).max() <= 1e-10 * np.abs(b).max()


def test_residual_of_a_stress_filled_at_the_solution_strain():
    """Fill S = sigma(u), E = e(u) at the points of a solved elastic problem and C = 0: the
    residual is still zero at the free dofs (the first-order term vanishes there)."""
    q = filled_elastic(2, "qs_res_")
    q.solve()
    Q = q.state.committed["strain"].function_space
    e = fem.Function(Q)
    e.interpolate(fem.Expression(q.model.strain(q.split(q.w)[0]), Q.element.interpolation_points))
    k = 3
    c = elastic_tangent(LAM, MU, 2)
    n = len(q.state.owned("strain")) // k
    strain = e.x.array[: n * k].reshape(n, k)
    fill(q.state, "stress", strain @ c.T)
    fill(q.state, "strain", strain)
    fill(q.state, "tangent", np.zeros((n, k, k)))
    from dolfinx.fem.petsc import assemble_vector

    b = assemble_vector(fem.form(q.residual()))
    b.ghostUpdate(addv=2, mode=1)  # ADD, REVERSE
    free = np.ones(b.getLocalSize(), bool)
    for bc in q.bcs:
        dofs = bc.dof_indices()[0]
        free[dofs[dofs < len(free)]] = False
    scale = np.abs(b.array_r).max()
    assert np.abs(b.array_r[free]).max() <= 1e-10 * max(scale, 1.0)
    b.destroy()


def test_bad_material_and_fill_are_refused():
    with pytest.raises(ValueError, match="QuadratureStressMaterial.rho"):
        QuadratureStressMaterial(rho=-1.0)
    q = filled_elastic(2, "qs_bad_")
    with pytest.raises(ValueError, match="fill 'stress'"):
        fill(q.state, "stress", np.zeros(7))
