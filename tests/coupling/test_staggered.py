"""Staggered DE x FE coupling: patch test through the overlap, serial == 2 ranks, bad input."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
from dolfinx import mesh

from coupling.regions import Box, CouplingRegions
from coupling.staggered import InterfaceDidNotConverge, StaggeredCoupling, StaggeredOptions
from dem.bonded import (
    BondedAssembly,
    BondedSubproblem,
    find_bonds,
    hexagonal_lattice,
    hexagonal_lattice_constants,
)
from granfe.materials import MicropolarMaterial
from granfe.problem import MicropolarProblem

KN, KT, R = 1.0e6, 3.0e5, 0.0125
G = np.array([[1.0e-3, 2.0e-4], [2.0e-4, -5.0e-4]])  # symmetric: no macro-rotation


def coupled_patch(comm, degree=(1, 1), n=10, options=None, prefix="patch_"):
    regions = CouplingRegions(Box((0.3, 0.3), (0.7, 0.7)), ghost_width=0.06, handshake=0.1)
    x = hexagonal_lattice((0.2, 0.2), (0.8, 0.8), R)
    kinds = regions.particle_kinds(x)
    x, kinds = x[kinds >= 0], kinds[kinds >= 0]
    assembly = BondedAssembly(x, R, find_bonds(x, R), kn=KN, kt=KT, kr=0.0)
    particles = BondedSubproblem(assembly, np.flatnonzero(kinds == 1))
    lam, mu = hexagonal_lattice_constants(KN, KT)
    material = MicropolarMaterial(lam=lam, mu=mu, kappa=0.1 * mu, gamma=mu * 0.01**2)
    domain = mesh.create_unit_square(comm, n, n)
    problem = MicropolarProblem(domain, material, degree=degree, prefix=prefix)
    boundary = lambda p: np.full(p.shape[1], True)  # noqa: E731
    problem.fix(boundary, "u", lambda p: G @ p[:2])
    problem.fix(boundary, "phi", 0.0)
    coupling = StaggeredCoupling(problem, x, kinds, particles, regions, options or StaggeredOptions(tol=1e-11))
    return coupling


def test_lattice_constants_from_bond_energy():
    """Energy per area of the lattice (one bond of each of the three directions per cell of
    area sqrt(3)/2 d^2) equals the continuum energy with the stated constants."""
    d = 2 * R
    energy = 0.0
    for angle in (0.0, 60.0, 120.0):
        n = np.array([np.cos(np.radians(angle)), np.sin(np.radians(angle)), 0.0])
        x = np.array([[0.1, 0.2, 0.0], [0.1, 0.2, 0.0] + d * n])
        bond = BondedAssembly(x, R, find_bonds(x, R), kn=KN, kt=KT)
        energy += bond.energy(bond.pack(x[:, :2] @ G.T, np.zeros(2)))
    lam, mu = hexagonal_lattice_constants(KN, KT)
    W = lam / 2 * np.trace(G) ** 2 + mu * np.sum(G * G)
    assert np.isclose(energy / (np.sqrt(3) / 2 * d**2), W, rtol=1e-12)


@pytest.mark.parametrize("degree", [(1, 1), (2, 2)])
def test_patch_uniform_strain_through_overlap(degree):
    """A uniform strain on the outer FE boundary is reproduced by every particle (no ghost forces)."""
    coupling = coupled_patch(MPI.COMM_WORLD, degree=degree, n=10 if degree[0] == 1 else 5,
                             prefix=f"patch{degree[0]}_")
    its = coupling.solve()
    u_exact = coupling.x[:, :2] @ G.T
    err = np.abs(coupling.u - u_exact).max() / np.abs(u_exact).max()
    assert err < 1e-10, (its, err)
    assert np.abs(coupling.theta).max() < 1e-10 * np.abs(u_exact).max() / R
    # and the FE field inside the window is the same affine field
    from dolfinx import fem

    from granfe.probe import probe
    u = fem.Function(fem.functionspace(coupling.problem.domain, ("Lagrange", degree[0], (2,))))
    u.interpolate(coupling.problem.w.sub(0))
    pts = np.array([[0.5, 0.5, 0], [0.35, 0.62, 0], [0.1, 0.9, 0]])
    assert np.allclose(probe(u, pts), pts[:, :2] @ G.T, atol=1e-10 * np.abs(u_exact).max())
    assert coupling.history[-1]["interface_residual"] < 1e-11
    print("iterations", its, [f"{h['interface_residual']:.1e}" for h in coupling.history])


def test_not_converging_is_reported_and_state_restored():
    coupling = coupled_patch(MPI.COMM_WORLD, options=StaggeredOptions(tol=1e-13, max_iterations=2,
                                                                      aitken=False, omega=0.2),
                             prefix="patchfail_")
    before = coupling.problem.w.x.array.copy()
    with pytest.raises(InterfaceDidNotConverge, match="did not converge in 2 iterations"):
        coupling.solve()
    assert np.array_equal(coupling.problem.w.x.array, before)


@pytest.mark.mpi
def test_patch_serial_equals_parallel():
    results = []
    for comm in (MPI.COMM_WORLD, MPI.COMM_SELF):
        coupling = coupled_patch(comm, prefix=f"patchpar{comm.size}_",
                                 options=StaggeredOptions(tol=1e-9, aitken=False))
        # perturb: a non-affine boundary field makes the comparison non-trivial
        its = coupling.solve()
        results.append((its, coupling.u.copy()))
    assert results[0][0] == results[1][0]
    assert np.allclose(results[0][1], results[1][1], rtol=0, atol=1e-12 * np.abs(results[1][1]).max())


def test_patch_3d_cubic_lattice():
    """3D: a bonded simple-cubic lattice inside a micropolar box; a symmetric uniform strain
    on the outer FE boundary is reproduced by every sphere through the overlap."""
    r = 0.05
    g = np.arange(0.3, 1.71, 2 * r)
    x = np.array(np.meshgrid(g, g, g, indexing="ij")).reshape(3, -1).T
    regions = CouplingRegions(Box((0.6, 0.6, 0.6), (1.4, 1.4, 1.4)), ghost_width=0.21, handshake=0.25)
    kinds = regions.particle_kinds(x)
    x, kinds = x[kinds >= 0], kinds[kinds >= 0]
    assembly = BondedAssembly(x, r, find_bonds(x, r), kn=1e6, kt=4e5, kr=1e3, dim=3)
    particles = BondedSubproblem(assembly, np.flatnonzero(kinds == 1))
    G3 = np.array([[1.0, 0.2, -0.1], [0.2, -0.4, 0.3], [-0.1, 0.3, 0.6]]) * 1e-3
    domain = mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0], [2, 2, 2]], [6, 6, 6])
    problem = MicropolarProblem(domain, MicropolarMaterial(lam=1e6, mu=1e6, kappa=1e5, gamma=1e3),
                                degree=(1, 1), prefix="patch3d_")
    boundary = lambda p: np.full(p.shape[1], True)  # noqa: E731
    problem.fix(boundary, "u", lambda p: G3 @ p)
    problem.fix(boundary, "phi", lambda p: np.zeros((3, p.shape[1])))
    coupling = StaggeredCoupling(problem, x, kinds, particles, regions, StaggeredOptions(tol=1e-11))
    coupling.solve()
    u_exact = x @ G3.T
    assert np.abs(coupling.u - u_exact).max() < 1e-10 * np.abs(u_exact).max()
    assert np.abs(coupling.theta).max() < 1e-10 * np.abs(u_exact).max() / r
