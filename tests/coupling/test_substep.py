"""The DEM phase of a coupled FE step (`coupling.substep`): the ghosts follow the continuum's
displacement and rotation at them.

Tolerance: 1e-13 relative (a rigid rotation u = W x is in the degree-1 space, its phi or
theta constant: every interpolation at the ghosts is exact; the DEM writes the prescribed
values).
"""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
from dolfinx import mesh

import dem
from coupling.interface import CouplingInterface
from coupling.regions import Box, CouplingRegions
from coupling.substep import GhostMotion, sub_cycle
from granfe.materials import MicropolarMaterial
from granfe.models.micromorphic import Micromorphic, MicromorphicMaterial
from granfe.models.micropolar import Micropolar
from granfe.problem import ContinuumProblem


def spin_matrix(t):
    """W with W v = t x v."""
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def continuum(comm, model, dim):
    msh = mesh.create_unit_square(comm, 2, 2) if dim == 2 else mesh.create_unit_cube(comm, 2, 2, 2)
    if model == "micromorphic":
        m = Micromorphic(MicromorphicMaterial.micropolar_limit(2e6, 1e6, 3e5, 10.0, penalty=1e6))
    else:
        m = Micropolar(MicropolarMaterial(lam=2e6, mu=1e6, kappa=3e5, gamma=10.0))
    return ContinuumProblem(msh, m, degree=(1, 1))


def grains(dim, spacing=0.1, radius=0.02):
    """A lattice of spheres apart from each other (no contacts: each moves as prescribed or
    not at all) over the unit square / cube, kinds 0 (window) and 1 (ghost band)."""
    g = np.arange(0.05, 1.0, spacing)
    x = np.stack(np.meshgrid(*[g] * dim, indexing="ij"), -1).reshape(-1, dim)
    regions = CouplingRegions(Box((0.3,) * dim, (0.7,) * dim), ghost_width=0.2, handshake=0.0)
    kinds = regions.particle_kinds(x)
    keep = kinds >= 0
    x3 = np.c_[x[keep], np.zeros((keep.sum(), 3 - dim))]
    return x3, kinds[keep].astype(np.int8), regions, radius


@pytest.mark.mpi
@pytest.mark.parametrize("model, dim", [("micromorphic", 3), ("micromorphic", 2), ("micropolar", 3)])
def test_a_rigid_rotation_of_the_continuum_turns_the_ghosts(model, dim):
    """The continuum turned rigidly by theta over one FE step (u = W x; phi = W, or the
    micropolar theta): over the DEM sub-cycle every ghost ends at X + W X, moving at
    W X / dt_fe and spinning at theta / dt_fe (closed form); the window's grains stay."""
    comm = MPI.COMM_WORLD
    p = continuum(comm, model, dim)
    x, kinds, regions, r = grains(dim)
    iface = CouplingInterface(p, x, kinds, regions)
    start = iface.ghost_motion()
    theta = np.array([0.0, 0.0, 0.03]) if dim == 2 else np.array([0.01, -0.02, 0.03])
    W = spin_matrix(theta)[:dim, :dim]
    p.w.sub(0).interpolate(lambda y: W @ y[:dim])
    if model == "micromorphic":
        p.w.sub(1).interpolate(lambda y: np.tile(W.reshape(-1, 1), y.shape[1]))
    else:
        p.w.sub(1).interpolate(lambda y: np.tile(theta[3 - dim:].reshape(-1, 1) if dim == 3
                                                 else theta[2:].reshape(-1, 1), y.shape[1]))
    p.w.x.scatter_forward()
    end = iface.ghost_motion()
    kind = np.where(kinds == 1, dem.GHOST, 0).astype(np.int8)
    particles = dem.Particles.spheres(x, r, 2650.0, dim=dim, kind=kind)
    sim = dem.Simulation(particles, dem.ContactMaterial(E=2.9e7, nu=0.25, density=2650.0, friction=0.5,
                                                        restitution=0.5),
                         gravity=(0.0, 0.0, 0.0))
    steps = 7
    dt_fe = steps * sim.dt
    rows = np.flatnonzero(kinds == 1)
    ghosts = GhostMotion(rows, x[rows], start[0], end[0], dt_fe, theta_start=start[1], theta_end=end[1])
    sub_cycle(sim, steps, (np.zeros(0, np.int64), np.zeros((0, 3))), 0.0, 0.0, dim - 1, ghosts)
    X = x[rows, :dim]
    assert np.abs(sim.p.x[rows, :dim] - (X + X @ W.T)).max() < 1e-13
    assert np.abs(sim.p.v[rows, :dim] - X @ W.T / dt_fe).max() < 1e-13 * np.abs(X @ W.T / dt_fe).max()
    spin = np.broadcast_to(theta / dt_fe, (len(rows), 3))
    assert np.abs(sim.p.omega[rows] - spin).max() < 1e-13 * np.abs(spin).max()
    free = np.flatnonzero(kinds == 0)
    assert np.array_equal(sim.p.x[free], x[free]) and not sim.p.omega[free].any()


def test_ghost_motion_without_a_rotation_leaves_the_spin():
    """No theta: the translation only, the ghosts' spin untouched (None to the DEM)."""
    rows, base = np.arange(3), np.zeros((3, 3))
    assert GhostMotion(rows, base, np.zeros((3, 3)), np.ones((3, 3)), 0.1).motion().omega is None
    with pytest.raises(ValueError, match="theta_start and theta_end are given together"):
        GhostMotion(rows, base, np.zeros((3, 3)), np.ones((3, 3)), 0.1, theta_start=np.zeros(3))
