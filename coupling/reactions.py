"""The force-carrying (Dirichlet-Neumann) exchange: ghosts follow the FE, their reactions load
it.

In the overlapping exchange (:class:`coupling.interface.CouplingInterface`) the FE nodes inside
the window are prescribed from the grains and the ghosts from the FE: displacements both ways,
so a linear continuum's displacement field does not depend on its stiffness and the window's
edge never feels the far field's compliance. Here the grains still see ghosts that move with
the FE (``Q^ = N D``, seed 001 eq. 74-78), but nothing of the FE is prescribed: the forces the
free grains exert on the ghosts (the DEM run with ``prescribed_pairs=False``, so a ghost's force
is that reaction alone) are handed back as nodal loads ``N^T f`` on the continuum, whose
material is taken out of the window by a partition weight (seed 001's energy partition with the
grains' share one inside the window, the continuum's outside). The window's edge then moves as
much as the continuum around it yields to the grains' push.
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401

import numpy as np
from dolfinx import fem

from coupling.interface import CouplingInterface, DistributedVectors, gather_rows
from coupling.locate import owner_ranks
from coupling.operators import FieldBasis

__all__ = ["GhostReactions", "window_weight"]


class GhostReactions(DistributedVectors):
    """Ghost motion from the FE fields and the ghosts' reactions as nodal loads on ``u``.

    Args:
        problem: a :class:`granfe.problem.ContinuumProblem` with fields ``u`` (degree 1) and
            ``phi``; a nodal load on ``u`` is added to it.
        x: centroids (n, 3) of every coupled particle (reference positions), identical on
            all ranks.
        kinds: (n,) 0 free, 1 ghost.
    """

    def __init__(self, problem, x, kinds):
        super().__init__(problem.domain.comm)
        self.problem = problem
        self.gdim = gdim = problem.domain.geometry.dim
        x, kinds = np.asarray(x, dtype=float), np.asarray(kinds)
        if x.ndim != 2 or x.shape[1] != 3 or len(kinds) != len(x):
            raise ValueError(f"x must be (n, 3) and kinds (n,), got {x.shape} and {kinds.shape}")
        self.ghost_index = np.flatnonzero(kinds == 1)
        owners = owner_ranks(problem.domain, x[self.ghost_index, :gdim])
        self._ghost_mine = np.flatnonzero(owners == self.comm.rank)
        points = x[self.ghost_index[self._ghost_mine], :gdim]
        self.bases = [FieldBasis.build(problem.V, points, sub=sub)
                      for sub in CouplingInterface.coupled_fields(problem)]
        self.load = problem.nodal_load("u")
        # the FE function the exchange writes (the prescribed values of the overlapping
        # exchange; here the nodal load's carrier): what a checkpoint keeps
        self.g = self.load.g
        self._vec = self.bases[0].matrix.createVecLeft()
        self._out = fem.Function(problem.V)

    def ghost_motion(self, w: fem.Function | None = None):
        """(u_ghost (n_g, dim), theta_ghost (n_g,) or (n_g, 3)) on every rank: ``Q^ = N D``."""
        w = self.problem.w if w is None else w
        u, theta = (gather_rows(self.comm, b.interpolate(w), self._ghost_mine, len(self.ghost_index))
                    for b in self.bases)
        return u, (theta[:, 0] if self.gdim == 2 else theta)

    def apply(self, f: np.ndarray) -> None:
        """Load the continuum with forces ``f`` (n_g, >= dim) [N] at the ghosts (identical on
        every rank): ``F = N^T f`` on the u dofs. Collective."""
        f = np.asarray(f, dtype=float)
        if f.shape[0] != len(self.ghost_index):
            raise ValueError(f"one force per ghost ({len(self.ghost_index)}), got {f.shape}")
        A = self.bases[0].matrix
        self._vec.setArray(np.ascontiguousarray(f[self._ghost_mine, : self.gdim]).ravel())
        A.multTranspose(self._vec, self._out.x.petsc_vec)
        self._out.x.scatter_forward()
        self.load.set(self._out.x.array)


def window_weight(domain, inside, floor: float = 1e-6) -> fem.Function:
    """The continuum's partition weight (DG0): ``floor`` on the cells whose every vertex
    ``inside`` (points (n, 3) -> bool mask) holds (the grains carry the material there), 1
    elsewhere. A cell reaching outside keeps the material: a ghost beside the window (outside
    it) then always loads a cell with stiffness, never nodes held by the floor alone. The
    floor keeps the window's nodes in the system (they carry nothing)."""
    V = fem.functionspace(domain, ("DG", 0))
    tdim = domain.topology.dim
    n = domain.topology.index_map(tdim).size_local + domain.topology.index_map(tdim).num_ghosts
    nodes = domain.geometry.dofmaps[0][:n]
    held = inside(domain.geometry.x[nodes.ravel()]).reshape(nodes.shape).all(axis=1)
    weight = fem.Function(V, name="partition_weight")
    weight.x.array[V.dofmap.list[:n, 0]] = np.where(held, floor, 1.0)
    return weight
