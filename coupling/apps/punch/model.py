"""The 2D bonded-punch set-up: a block of bonded grains, its micropolar continuum, and the
coupled DE window under a rough flat punch (shared by the demo, the runner and benchmarks)."""

from __future__ import annotations

from dataclasses import dataclass

import dolfinx_solver  # noqa: F401

import numpy as np
from dolfinx import mesh

from coupling.regions import Box, CouplingRegions
from coupling.staggered import StaggeredCoupling, StaggeredOptions
from dem.bonded import (
    BondedAssembly,
    BondedSubproblem,
    find_bonds,
    hexagonal_lattice,
    hexagonal_lattice_micropolar,
)
from granfe.materials import MicropolarMaterial
from granfe.problem import MicropolarProblem

__all__ = ["PunchBlock", "lattice_block", "fe_block", "coupled_window", "CoupledPunch"]


@dataclass
class PunchBlock:
    """Grains of the whole block and what the continuum needs to know about them."""

    x: np.ndarray            # (n, 3) grain centres [m]
    radius: float
    kn: float
    kt: float
    kr: float
    punch: np.ndarray        # grains under the punch (top row)
    base: np.ndarray         # grains on the base
    width: float
    material: MicropolarMaterial

    @property
    def top(self) -> float:
        """Height of the top row of grain centres [m]."""
        return float(self.x[:, 1].max())

    @property
    def surface(self) -> float:
        """Height of the continuum's free surface: half a row spacing above the top row [m]."""
        return self.top + np.sqrt(3) / 2 * self.radius

    @property
    def centre(self) -> float:
        return float(0.5 * (self.x[:, 0].min() + self.x[:, 0].max()))


def lattice_block(width, height, radius, kn, kt, kr_factor, punch_width) -> PunchBlock:
    """Hexagonal bonded packing filling ``[0, width] x [0, height]`` and its continuum constants."""
    d = 2 * radius
    x = hexagonal_lattice((0, 0), (width, height), radius)
    kr = kr_factor * kt * d**2
    top = x[:, 1] > x[:, 1].max() - 0.5 * d
    centre = 0.5 * (x[:, 0].min() + x[:, 0].max())
    punch = np.flatnonzero(top & (np.abs(x[:, 0] - centre) < punch_width / 2))
    base = np.flatnonzero(x[:, 1] < x[:, 1].min() + 0.5 * d)
    material = MicropolarMaterial(**hexagonal_lattice_micropolar(kn, kt, kr))
    return PunchBlock(x, radius, kn, kt, kr, punch, base, punch_width, material)


def fe_block(comm, block: PunchBlock, element_size: float, degree=(2, 2), prefix="block_",
             checkpoint_dir=None) -> MicropolarProblem:
    """Micropolar FE block carrying the grains' cells, base clamped (u = 0, phi = 0).

    The block reaches half a grain spacing beyond the outer grain centres (r in x,
    sqrt(3)/4 d above the top row) so that its mass and stiffness are the lattice's; its
    base is the row of clamped grains' centres."""
    x = block.x
    d = 2 * block.radius
    lo = x[:, :2].min(axis=0) - np.array([block.radius, 0.0])
    hi = x[:, :2].max(axis=0) + np.array([block.radius, np.sqrt(3) / 4 * d])
    n = np.maximum(np.round((hi - lo) / element_size).astype(int), 1)
    domain = mesh.create_rectangle(comm, [lo, hi], n)
    problem = MicropolarProblem(domain, block.material, degree=tuple(degree), prefix=prefix,
                                checkpoint_dir=checkpoint_dir)
    base = lambda p: np.isclose(p[1], lo[1])  # noqa: E731
    problem.fix(base, "u")
    problem.fix(base, "phi")
    return problem


@dataclass
class CoupledPunch:
    """The bonded punch set up for a staggered coupled solve."""

    coupling: StaggeredCoupling
    particles: BondedSubproblem
    keep: np.ndarray        # indices into the block's grains
    punch: np.ndarray       # punch grains, indices into the window's grains

    def press(self, settlement: float) -> int:
        """Solve the coupled problem with the punch grains pushed down by ``settlement``."""
        self.particles.fixed_u[:, 0] = 0.0
        self.particles.fixed_u[:, 1] = -settlement
        return self.coupling.solve()

    def punch_force(self) -> float:
        """Vertical force the punch applies [N per m thickness], positive pushing down."""
        a = self.particles.assembly
        f = (a.K @ self.particles.q).reshape(len(a.x), -1)
        return float(-f[self.punch, 1].sum())


def coupled_window(block: PunchBlock, problem: MicropolarProblem, half_width: float, depth: float,
                   ghost_width: float, handshake: float, options: StaggeredOptions) -> CoupledPunch:
    """Window of free grains under the punch, a ghost band around it, FE nodes prescribed
    deeper than ``handshake`` [m] inside it. ``ghost_width`` in metres."""
    c, top = block.centre, block.top
    # the box reaches above the free surface so the overlap runs only along its sides and base
    window = Box((c - half_width, top - depth), (c + half_width, top + depth))
    regions = CouplingRegions(window, ghost_width=ghost_width, handshake=handshake)
    kinds = regions.particle_kinds(block.x)
    keep = np.flatnonzero(kinds >= 0)
    x, kinds = block.x[keep], kinds[keep]
    punch = np.flatnonzero(np.isin(keep, block.punch))
    if len(punch) != len(block.punch):
        raise ValueError("the punch is wider than the DE window")
    kinds[punch] = 0  # punch grains move with the punch: fixed on the particle side, free for the FE
    assembly = BondedAssembly(x, block.radius, find_bonds(x, block.radius), block.kn, block.kt, block.kr)
    particles = BondedSubproblem(assembly, np.flatnonzero(kinds == 1), punch)
    coupling = StaggeredCoupling(problem, x, kinds, particles, regions, options)
    return CoupledPunch(coupling, particles, keep, punch)
