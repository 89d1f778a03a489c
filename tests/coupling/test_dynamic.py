"""Dynamic DE x FE coupling: a uniform motion passes the overlap unchanged; serial == 2 ranks."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
from dolfinx import mesh

from coupling.dynamic import DynamicCoupling, DynamicOptions
from coupling.regions import Box, CouplingRegions
from dem.bonded import (
    BondedAssembly,
    BondedDynamics,
    find_bonds,
    hexagonal_lattice,
    hexagonal_lattice_micropolar,
)
from granfe.materials import MicropolarMaterial
from granfe.problem import MicropolarProblem

R, KN, KT = 0.005, 1.0e8, 3.0e7


def strip(comm, prefix, v0=(0.0, 0.0)):
    kr = 0.1 * KT * (2 * R) ** 2
    rho = 2650.0
    material = MicropolarMaterial(**hexagonal_lattice_micropolar(KN, KT, kr),
                                  rho=rho * np.pi / (2 * np.sqrt(3)), j=R**2 / 2)
    grains = hexagonal_lattice((0, 0), (0.6, 0.06), R)
    y0, y1, x1 = grains[:, 1].min(), grains[:, 1].max(), grains[:, 0].max()
    regions = CouplingRegions(Box((0.3, y0 - 1), (x1 + 1, y1 + 1)), ghost_width=0.025, handshake=0.05)
    kinds = regions.particle_kinds(grains)
    keep = kinds >= 0
    x, kinds = grains[keep], kinds[keep]
    particles = BondedDynamics(BondedAssembly(x, R, find_bonds(x, R), KN, KT, kr), rho,
                               np.flatnonzero(kinds == 1))
    domain = mesh.create_rectangle(comm, [[0.0, y0], [x1, y1]], [24, 2])
    problem = MicropolarProblem(domain, material, degree=(2, 2), prefix=prefix)
    coupling = DynamicCoupling(problem, 1e-4, x, kinds, particles, regions, DynamicOptions(tol=1e-10))
    particles.v.reshape(len(x), 3)[:, :2] = v0
    coupling.stepper.v.sub(0).interpolate(lambda p: np.vstack([np.full(p.shape[1], v0[0]),
                                                               np.full(p.shape[1], v0[1])]))
    return coupling


def test_uniform_motion_is_kept():
    v0 = (0.3, -0.1)
    coupling = strip(MPI.COMM_WORLD, "dynuni_", v0)
    for _ in range(5):
        coupling.step()
    u, theta = coupling.particles.motion()
    t = coupling.t
    assert np.allclose(u, np.array(v0) * t, rtol=0, atol=1e-10 * np.abs(v0).max() * t)
    assert np.abs(theta).max() < 1e-9
    kin, _ = coupling.stepper.energies()
    assert kin > 0


@pytest.mark.mpi
def test_dynamic_serial_equals_parallel():
    results = []
    for comm in (MPI.COMM_WORLD, MPI.COMM_SELF):
        coupling = strip(comm, f"dynpar{comm.size}_")
        coupling.stepper.v.sub(0).interpolate(
            lambda p: np.vstack([0.1 * np.exp(-((p[0] - 0.15) / 0.05) ** 2), 0 * p[0]]))
        for _ in range(5):
            coupling.step()
        results.append(coupling.particles.q.copy())
    scale = np.abs(results[1]).max()
    assert scale > 0
    assert np.allclose(results[0], results[1], rtol=0, atol=1e-8 * scale)
