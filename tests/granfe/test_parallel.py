"""Serial and distributed solves agree to round-off (run under mpiexec -n 2 by `make test`)."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
from dolfinx import fem, mesh

from granfe.dynamics import GeneralizedAlpha
from granfe.materials import MicropolarMaterial
from granfe.probe import probe
from granfe.problem import MicropolarProblem

MAT = MicropolarMaterial.from_engineering(1.0e9, 0.3, length=0.05, kappa_over_mu=0.5, rho=2000.0)
POINTS = np.array([[1.0, 0.1, 0.0], [0.5, 0.2, 0.0], [0.25, 0.0, 0.0], [0.7, 0.13, 0.0]])


def cantilever(comm, gdim):
    if gdim == 2:
        domain = mesh.create_rectangle(comm, [[0, 0], [1, 0.2]], [12, 3])
        t = (1e5, -1e5)
    else:
        domain = mesh.create_box(comm, [[0, 0, 0], [1, 0.2, 0.2]], [6, 2, 2])
        t = (1e5, -1e5, 5e4)
    problem = MicropolarProblem(domain, MAT, prefix=f"par{gdim}{comm.size}_")
    problem.fix(lambda x: np.isclose(x[0], 0.0), "u")
    problem.fix(lambda x: np.isclose(x[0], 0.0), "phi")
    problem.traction(lambda x: np.isclose(x[0], 1.0), t)
    return problem


def sample(problem):
    gdim = problem.gdim
    u = fem.Function(fem.functionspace(problem.domain, ("Lagrange", 2, (gdim,))))
    u.interpolate(problem.w.sub(0))
    pts = POINTS.copy()
    if gdim == 3:
        pts[:, 2] = 0.1
    return probe(u, pts)


@pytest.mark.mpi
@pytest.mark.parametrize("gdim", [2, 3])
def test_static_serial_equals_parallel(gdim):
    world = cantilever(MPI.COMM_WORLD, gdim)
    world.solve()
    alone = cantilever(MPI.COMM_SELF, gdim)
    alone.solve()
    a, b = sample(world), sample(alone)
    assert np.allclose(a, b, rtol=1e-11, atol=1e-13 * np.abs(b).max())


@pytest.mark.mpi
def test_dynamics_serial_equals_parallel():
    results = []
    for comm in (MPI.COMM_WORLD, MPI.COMM_SELF):
        problem = cantilever(comm, 2)
        stepper = GeneralizedAlpha(problem, 1e-5, rho_inf=0.9, prefix=f"pardyn{comm.size}_")
        for _ in range(20):
            stepper.step()
        results.append((sample(problem), sum(stepper.energies())))
    (a, ea), (b, eb) = results
    assert np.allclose(a, b, rtol=1e-10, atol=1e-12 * np.abs(b).max())
    assert abs(ea - eb) < 1e-10 * abs(eb)
