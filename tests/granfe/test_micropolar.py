"""2D/3D micropolar elasticity: manufactured solutions, classical limit, patch test, bad input."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
import ufl
from dolfinx import fem, mesh
from dolfinx.fem.petsc import LinearProblem

from granfe.manufactured import everywhere, rates
from granfe.materials import MicropolarMaterial
from granfe.problem import MicropolarProblem, MissingBoundary
from granfe.solvers import SolveDidNotConverge

MAT = MicropolarMaterial(lam=2.0, mu=1.0, kappa=0.5, alpha=0.3, beta=0.2, gamma=0.6)


# observed (16 -> 32) rates: P1/P1 2,1,2,1; P2/P2 3,2,3,2; P2/P1 2.26,2,2,1 (u_L2 is
# limited by the rotation's O(h^2) L2 error entering through the coupling term)
EXPECTED_RATES = {  # (u_L2, u_H1, phi_L2, phi_H1)
    (1, 1): (2, 1, 2, 1),
    (2, 2): (3, 2, 3, 2),
    (2, 1): (2, 2, 2, 1),
}


@pytest.mark.parametrize("degree", list(EXPECTED_RATES))
def test_manufactured_2d_rates(degree):
    meshes = [mesh.create_unit_square(MPI.COMM_WORLD, n, n) for n in (4, 8, 16)]
    r, _ = rates(meshes, degree)
    for key, expected in zip(("u_L2", "u_H1", "phi_L2", "phi_H1"), EXPECTED_RATES[degree], strict=False):
        assert r[key] > expected - 0.15, (key, r[key], expected)


def test_manufactured_3d_rates():
    meshes = [mesh.create_unit_cube(MPI.COMM_WORLD, n, n, n) for n in (2, 4)]
    r, _ = rates(meshes, (2, 2))
    assert r["u_L2"] > 2.6 and r["phi_L2"] > 2.6
    assert r["u_H1"] > 1.7 and r["phi_H1"] > 1.7


def classical_displacement(domain, lam, mu, traction, degree=2):
    """Plain DOLFINx linear elasticity, clamped at x = 0, traction at x = 1."""
    V = fem.functionspace(domain, ("Lagrange", degree, (domain.geometry.dim,)))
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)

    def sigma(w):
        eps = ufl.sym(ufl.grad(w))
        return lam * ufl.tr(eps) * ufl.Identity(len(w)) + 2 * mu * eps

    fdim = domain.topology.dim - 1
    left = mesh.locate_entities_boundary(domain, fdim, lambda x: np.isclose(x[0], 0.0))
    right = mesh.locate_entities_boundary(domain, fdim, lambda x: np.isclose(x[0], 1.0))
    tags = mesh.meshtags(domain, fdim, np.sort(right), np.full(len(right), 1, dtype=np.int32))
    ds = ufl.Measure("ds", domain=domain, subdomain_data=tags)
    bc = fem.dirichletbc(np.zeros(domain.geometry.dim), fem.locate_dofs_topological(V, fdim, left), V)
    t = fem.Constant(domain, np.array(traction, dtype=float))
    problem = LinearProblem(ufl.inner(sigma(u), ufl.grad(v)) * ufl.dx, ufl.inner(t, v) * ds(1),
                            bcs=[bc], petsc_options_prefix="classical_",
                            petsc_options={"ksp_type": "preonly", "pc_type": "lu",
                                           "pc_factor_mat_solver_type": "mumps"})
    return problem.solve()


def micropolar_cantilever(domain, material, traction):
    problem = MicropolarProblem(domain, material, prefix=f"cant{id(material)}_")
    clamp = lambda x: np.isclose(x[0], 0.0)  # noqa: E731
    problem.fix(clamp, "u")
    problem.fix(clamp, "phi")
    problem.traction(lambda x: np.isclose(x[0], 1.0), traction)
    problem.solve()
    return problem


@pytest.mark.parametrize("gdim", [2, 3])
def test_kappa_zero_is_classical_elasticity(gdim):
    """kappa = 0 decouples phi: u equals a plain elasticity solve on the same mesh to round-off."""
    comm = MPI.COMM_WORLD
    domain = (mesh.create_rectangle(comm, [[0, 0], [1, 0.3]], [10, 3]) if gdim == 2
              else mesh.create_box(comm, [[0, 0, 0], [1, 0.3, 0.3]], [6, 2, 2]))
    traction = (0.1, -0.05) if gdim == 2 else (0.1, -0.05, 0.02)
    mat = MicropolarMaterial(lam=1.5, mu=1.0, kappa=0.0, gamma=0.7)
    problem = micropolar_cantilever(domain, mat, traction)
    u_ref = classical_displacement(domain, 1.5, 1.0, traction)
    u = fem.Function(u_ref.function_space)
    u.interpolate(problem.w.sub(0))  # same element: a dof permutation, exact
    diff = comm.allreduce(np.max(np.abs(u.x.array - u_ref.x.array), initial=0.0), MPI.MAX)
    scale = comm.allreduce(np.max(np.abs(u_ref.x.array)), MPI.MAX)
    assert diff < 1e-10 * scale


def test_vanishing_moduli_converge_to_classical():
    """kappa > 0 with couple moduli -> 0: phi follows the macro-rotation, u tends to classical."""
    comm = MPI.COMM_WORLD
    domain = mesh.create_rectangle(comm, [[0, 0], [1, 0.3]], [10, 3])
    u_ref = classical_displacement(domain, 1.5, 1.0, (0.0, -0.05))
    gaps = []
    for kappa in (1e-3, 1e-5, 1e-7):
        mat = MicropolarMaterial(lam=1.5, mu=1.0, kappa=kappa, gamma=kappa)
        u = fem.Function(u_ref.function_space)
        u.interpolate(micropolar_cantilever(domain, mat, (0.0, -0.05)).w.sub(0))
        gaps.append(comm.allreduce(np.max(np.abs(u.x.array - u_ref.x.array)), MPI.MAX))
    scale = comm.allreduce(np.max(np.abs(u_ref.x.array)), MPI.MAX)
    # the gap closes linearly in the moduli (factor 100 per factor 100)
    assert gaps[0] / gaps[1] > 50 and gaps[1] / gaps[2] > 50
    assert gaps[2] < 1e-5 * scale


@pytest.mark.parametrize("gdim", [2, 3])
def test_constant_strain_patch(gdim):
    """Linear u with phi = macro-rotation: constant symmetric stress, zero couple stress,
    reproduced to round-off on a distorted unstructured mesh with no body loads."""
    comm = MPI.COMM_WORLD
    rng = np.random.default_rng(3)
    if gdim == 2:
        domain = mesh.create_unit_square(comm, 5, 4, diagonal=mesh.DiagonalType.crossed)
        G = np.array([[1.0, 0.3], [-0.2, 0.5]]) * 1e-3
    else:
        domain = mesh.create_unit_cube(comm, 3, 3, 2)
        G = np.array([[1.0, 0.3, -0.1], [-0.2, 0.5, 0.2], [0.4, 0.0, -0.3]]) * 1e-3
    x = domain.geometry.x
    interior = np.all((x[:, :gdim] > 1e-8) & (x[:, :gdim] < 1 - 1e-8), axis=1)
    x[interior, :gdim] += rng.uniform(-0.05, 0.05, (interior.sum(), gdim))
    W = 0.5 * (G - G.T)  # macro-rotation: skew(grad u); phi_k = -1/2 e_kij W_ij
    phi = (W[1, 0] if gdim == 2 else np.array([W[2, 1], W[0, 2], W[1, 0]]))
    problem = MicropolarProblem(domain, MAT, prefix=f"patch{gdim}_")
    problem.fix(everywhere, "u", lambda p: G @ p[:gdim])
    problem.fix(everywhere, "phi", (lambda p: np.full(p.shape[1], phi)) if gdim == 2
                else (lambda p: np.tile(phi[:, None], p.shape[1])))
    problem.solve()
    u, ph = problem.w.sub(0).collapse(), problem.w.sub(1).collapse()
    xu = u.function_space.tabulate_dof_coordinates()[:, :gdim]
    err_u = np.max(np.abs(u.x.array.reshape(-1, gdim) - xu @ G.T))
    err_phi = np.max(np.abs(ph.x.array - (phi if gdim == 2 else np.tile(phi, len(ph.x.array) // 3))))
    assert comm.allreduce(err_u, MPI.MAX) < 1e-13
    assert comm.allreduce(err_phi, MPI.MAX) < 1e-13


def test_missing_boundary_is_named():
    domain = mesh.create_unit_square(MPI.COMM_WORLD, 2, 2)
    fdim = 1
    facets = mesh.locate_entities_boundary(domain, fdim, lambda x: np.isclose(x[0], 0.0))
    tags = mesh.meshtags(domain, fdim, np.sort(facets), np.full(len(facets), 7, dtype=np.int32))
    problem = MicropolarProblem(domain, MAT, facet_tags=tags, tag_names={"left": 7, "right": 8})
    with pytest.raises(MissingBoundary, match="'hole' is not a physical group"):
        problem.fix("hole", "u")
    with pytest.raises(MissingBoundary, match=r"'right' \(tag 8\) has no facets"):
        problem.traction("right", (1.0, 0.0))
    with pytest.raises(ValueError, match="unknown component 'phi_x'"):
        problem.fix("left", "phi_x")
    with pytest.raises(ValueError, match="not finite"):
        problem.traction("left", (np.nan, 0.0))


def test_failed_solve_names_reason_and_keeps_last_good_state(tmp_path):
    comm = MPI.COMM_WORLD
    domain = mesh.create_unit_square(comm, 6, 6)
    out = comm.bcast(str(tmp_path), root=0)
    problem = MicropolarProblem(domain, MAT, prefix="fail_", checkpoint_dir=out,
                                petsc_options={"ksp_type": "cg", "pc_type": "none", "ksp_max_it": 1})
    problem.fix(lambda x: np.isclose(x[0], 0.0), "u")
    problem.fix(lambda x: np.isclose(x[0], 0.0), "phi")
    problem.traction(lambda x: np.isclose(x[0], 1.0), (1.0, 0.0))
    before = problem.w.x.array.copy()
    with pytest.raises(SolveDidNotConverge, match="DIVERGED_LINEAR_SOLVE.*last converged state written"):
        problem.solve()
    assert np.array_equal(problem.w.x.array, before)
    from pathlib import Path
    assert (Path(out) / f"continuum_rank{comm.rank}_of{comm.size}.npz").exists()


@pytest.mark.mpi
def test_iterative_and_redundant_solvers_match_direct():
    """Parallel MUMPS, sequential MUMPS on every rank (``redundant``) and CG + GAMG solve the
    same system (under MPI the redundant one is the run-to-run reproducible choice)."""
    domain = mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0], [1, 0.25, 0.25]], [8, 2, 2])
    sols = []
    for solver in ("direct", "iterative", "redundant"):
        problem = MicropolarProblem(domain, MAT, solver=solver, prefix=f"{solver}3d_")
        problem.fix(lambda x: np.isclose(x[0], 0.0), "u")
        problem.fix(lambda x: np.isclose(x[0], 0.0), "phi")
        problem.traction(lambda x: np.isclose(x[0], 1.0), (0.0, 0.0, -1e-3))
        problem.solve()
        sols.append(problem.w.x.array.copy())
    comm = MPI.COMM_WORLD
    scale = comm.allreduce(np.max(np.abs(sols[0])), MPI.MAX)
    assert comm.allreduce(np.max(np.abs(sols[0] - sols[1])), MPI.MAX) < 1e-6 * scale
    assert comm.allreduce(np.max(np.abs(sols[0] - sols[2])), MPI.MAX) < 1e-11 * scale
