"""The DE x FE interface: ghost motion from the FE fields, prescribed FE dofs from the
particles, and Aitken relaxation of the exchanged values (used by the static and the
dynamic staggered solvers)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
from dolfinx import fem

from coupling.locate import owner_ranks, relocate
from coupling.operators import FieldBasis, NodalProjection
from coupling.regions import CouplingRegions

__all__ = ["CouplingInterface", "Aitken"]


@dataclass
class _Field:
    sub: int
    ghost: FieldBasis
    free: FieldBasis
    projection: NodalProjection
    prescribed: np.ndarray  # owned local parent dofs


class CouplingInterface:
    """Operators between a continuum FE problem and a set of particles.

    Args:
        problem: a :class:`granfe.problem.ContinuumProblem` whose model has the fields
            ``u`` and ``phi`` (:meth:`coupled_fields`); a Dirichlet condition on the
            prescribed dofs (values in :attr:`g`) is added to it.
        x: centroids (n, 3) of every coupled particle, identical on all ranks.
        kinds: (n,) 0 free, 1 ghost.
        regions: gives the prescribed FE nodes.
        regularization: of the nodal projection.
        min_support: drop prescribed nodes whose particle support ``sum_p N_p(x_node)^2``
            (the diagonal of M) is below this fraction of the median: such nodes (a free
            surface, a cavity) would make the projection ill-conditioned and amplify noise;
            they stay FE dofs.
    """

    def __init__(self, problem, x, kinds, regions: CouplingRegions, regularization: float = 0.0,
                 min_support: float = 0.0):
        self.problem = problem
        V, domain = problem.V, problem.domain
        self.comm = comm = domain.comm
        self.gdim = gdim = domain.geometry.dim
        self.x = np.asarray(x, dtype=float)
        self.kinds = np.asarray(kinds)
        if self.x.ndim != 2 or self.x.shape[1] != 3 or len(self.kinds) != len(self.x):
            raise ValueError(f"x must be (n, 3) and kinds (n,), got {self.x.shape} and {self.kinds.shape}")
        if np.any((self.kinds != 0) & (self.kinds != 1)):
            raise ValueError("kinds must be 0 (free) or 1 (ghost); drop particles outside the "
                             "coupled region before coupling")
        t0 = time.perf_counter()
        self._locate(self.x)
        self.g = fem.Function(V, name="prescribed_values")
        bc_dofs, self.fields = [], []
        for sub in self.coupled_fields(problem):
            ghost = FieldBasis.build(V, self._ghost_points(self.x), sub=sub)
            free = FieldBasis.build(V, self._free_points(self.x), sub=sub)
            Vc, parent = V.sub(sub).collapse()
            parent = np.asarray(parent[0] if isinstance(parent, list) else parent, dtype=np.int64)
            bs = Vc.dofmap.bs
            coords = np.repeat(Vc.tabulate_dof_coordinates(), bs, axis=0)[: parent.size]
            local = parent[regions.prescribed_nodes(coords[:, :gdim])]
            if min_support > 0:
                local = self._supported(V, free, local, min_support)
            owned = local[local < V.dofmap.index_map.size_local * V.dofmap.index_map_bs]
            projection = NodalProjection(free, owned, regularization)
            self.fields.append(_Field(sub, ghost, free, projection, np.sort(owned)))
            bc_dofs.append(local)
        self.regularization = regularization
        self.update_counts = {"updates": 0, "changed_cell": 0, "changed_rank": 0,
                              "pattern_rebuilds": 0, "full_rebuilds": 0}
        self.n_prescribed = comm.allreduce(sum(f.prescribed.size for f in self.fields))
        if self.n_prescribed == 0:
            raise ValueError("no FE dofs are prescribed: the window is smaller than the "
                             "handshake depth or the mesh has no nodes inside it")
        dofs = np.unique(np.concatenate(bc_dofs)).astype(np.int32)
        problem.bcs.append(fem.dirichletbc(self.g, dofs))
        # the FE problem is linear and only the Dirichlet values change between solves:
        # factorise the Jacobian once and reuse it
        problem.petsc_options.setdefault("snes_lag_jacobian", -2)
        problem.petsc_options.setdefault("snes_lag_jacobian_persists", True)
        problem.invalidate()
        self.setup_time = time.perf_counter() - t0

    @staticmethod
    def coupled_fields(problem) -> tuple[int, int]:
        """Indices of the fields the particles drive: ``u`` (their translations) and ``phi``
        (their rotations). A continuum model coupled to grains must declare both."""
        names = [f.name for f in problem.fields]
        missing = [n for n in ("u", "phi") if n not in names]
        if missing:
            raise ValueError(f"the grains drive the fields u and phi; the {problem.model.name} "
                             f"model has {names} (missing {missing})")
        return names.index("u"), names.index("phi")

    def _locate(self, x: np.ndarray) -> None:
        """Which particles this rank holds (the owner of the cell containing each centroid)."""
        owners = owner_ranks(self.problem.domain, x[:, : self.gdim])
        mine = owners == self.comm.rank
        self._owners = owners
        self.ghost_index = np.flatnonzero(self.kinds == 1)
        self.free_index = np.flatnonzero(self.kinds == 0)
        self._ghost_mine = np.flatnonzero(mine[self.ghost_index])  # positions within ghost list
        self._free_mine = self.free_index[mine[self.free_index]]    # particle indices

    @property
    def free_owned(self) -> np.ndarray:
        """Indices of the free particles whose centroids lie in this rank's cells."""
        return self._free_mine

    def _ghost_points(self, x: np.ndarray) -> np.ndarray:
        return x[self.ghost_index[self._ghost_mine], : self.gdim]

    def _free_points(self, x: np.ndarray) -> np.ndarray:
        return x[self._free_mine, : self.gdim]

    def update_positions(self, x: np.ndarray) -> dict:
        """Move the coupled particles (same particles and kinds) to centroids x (n, 3).

        Cheapest path first: each rank checks whether its particles are still inside their
        cells (a pull-back to the reference cell) and searches only for those that left;
        every row of N is re-evaluated (values change inside a cell too), and the sparsity
        of N and M plus the symbolic factorisation of M are rebuilt only if some particle
        changed cell. If a particle left its rank's cells, ownership is recomputed and the
        operators are built anew (the prescribed dofs and the Dirichlet condition are kept).
        Collective; the result equals a fresh :class:`CouplingInterface` at x to round-off.

        Returns:
            this call's counts: changed_cell (particles that changed cell, all ranks),
            changed_rank, pattern_rebuilt (bool), full_rebuild (bool). Running totals are
            kept in :attr:`update_counts`.
        """
        x = np.asarray(x, dtype=float)
        if x.shape != self.x.shape:
            raise ValueError(f"x must have shape {self.x.shape} (the same particles), "
                             f"got {x.shape}")
        domain = self.problem.domain
        located = []
        n_lost = 0
        for pts, basis in ((self._ghost_points(x), self.fields[0].ghost),
                           (self._free_points(x), self.fields[0].free)):
            cells, X, changed, lost = relocate(domain, pts, basis.cells)
            located.append((cells, X, changed))
            n_lost += int(lost.sum())
        counts = {"changed_cell": 0, "changed_rank": 0, "pattern_rebuilt": False,
                  "full_rebuild": False}
        if self.comm.allreduce(n_lost):
            old = self._owners
            self._locate(x)
            counts["changed_rank"] = int(np.count_nonzero(old != self._owners))
            counts["full_rebuild"] = counts["pattern_rebuilt"] = True
            for f in self.fields:
                f.ghost = FieldBasis.build(self.problem.V, self._ghost_points(x), sub=f.sub)
                f.free = FieldBasis.build(self.problem.V, self._free_points(x), sub=f.sub)
                f.projection = NodalProjection(f.free, f.prescribed, self.regularization)
        else:
            for f in self.fields:
                n_ghost = f.ghost.update(self._ghost_points(x), located[0])
                n_free = f.free.update(self._free_points(x), located[1])
                counts["pattern_rebuilt"] |= f.projection.update()
            counts["changed_cell"] = n_ghost + n_free
        self.x = x.copy()
        self.update_counts["updates"] += 1
        for key in ("changed_cell", "changed_rank"):
            self.update_counts[key] += counts[key]
        self.update_counts["pattern_rebuilds"] += int(counts["pattern_rebuilt"])
        self.update_counts["full_rebuilds"] += int(counts["full_rebuild"])
        return counts

    def _supported(self, V, basis, candidates, fraction):
        """The candidate dofs (local, owned and ghost) whose diagonal of M is large enough."""
        import dolfinx.la

        imap, bs = V.dofmap.index_map, V.dofmap.index_map_bs
        diag = dolfinx.la.vector(imap, bs)
        diag.array[:] = np.asarray(basis.local.multiply(basis.local).sum(axis=0)).ravel()
        diag.scatter_reverse(dolfinx.la.InsertMode.add)
        n_owned = imap.size_local * bs
        owned = candidates[candidates < n_owned]
        values = diag.array[owned]
        median = np.median(np.concatenate(self.comm.allgather(values)))
        mask = dolfinx.la.vector(imap, bs)
        mask.array[owned[values >= fraction * median]] = 1.0
        mask.scatter_forward()
        return candidates[mask.array[candidates] > 0.5]

    def norm(self, v: np.ndarray) -> float:
        return float(np.sqrt(self.comm.allreduce(float(v @ v), MPI.SUM)))

    def dot(self, a: np.ndarray, b: np.ndarray) -> float:
        return float(self.comm.allreduce(float(a @ b), MPI.SUM))

    def ghost_motion(self, w: fem.Function | None = None):
        """(u_ghost (n_g, dim), theta_ghost (n_g,) or (n_g, 3)) on every rank: ``Q^ = N D``."""
        w = self.problem.w if w is None else w
        out = []
        for f in self.fields:
            local = f.ghost.interpolate(w)
            parts = self.comm.allgather((self._ghost_mine, local))
            values = np.zeros((len(self.ghost_index), f.ghost.value_size))
            for idx, val in parts:
                values[idx] = val.reshape(len(idx), f.ghost.value_size)
            out.append(values)
        u, theta = out
        return u, (theta[:, 0] if self.gdim == 2 else theta)

    def project(self, u: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Prescribed-dof values (this rank's, u then phi) from all particles' motion."""
        w = self.problem.w
        th = np.reshape(theta, (len(theta), -1))
        return np.concatenate([f.projection.project(q[self._free_mine], w)
                               for f, q in zip(self.fields, (u[:, : self.gdim], th), strict=False)])

    def project_displacement(self, u: np.ndarray) -> np.ndarray:
        """The displacement part of :meth:`project` (this rank's prescribed u dofs) alone, for
        callers that keep the rotations' prescribed values: no projection of the rotations
        (its M^-1 solve and collectives) to throw away."""
        f = self.fields[0]
        return f.projection.project(np.asarray(u)[self._free_mine, : self.gdim], self.problem.w)

    def prescribed_values(self) -> np.ndarray:
        return np.concatenate([self.g.x.array[f.prescribed] for f in self.fields])

    def set_prescribed(self, values: np.ndarray) -> None:
        start = 0
        for f in self.fields:
            self.g.x.array[f.prescribed] = values[start: start + f.prescribed.size]
            start += f.prescribed.size
        self.g.x.scatter_forward()


class Aitken:
    """Aitken's dynamic relaxation of a fixed point ``x <- x + omega (T(x) - x)``."""

    def __init__(self, interface: CouplingInterface, omega: float = 1.0, enabled: bool = True,
                 bounds=(0.05, 2.0)):
        self.interface, self.omega0, self.enabled, self.bounds = interface, omega, enabled, bounds
        self.reset()

    def reset(self):
        self.omega, self.r_prev = self.omega0, None

    def update(self, current: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, float]:
        """New iterate and the relative residual ``|T(x) - x| / |T(x)|``."""
        r = target - current
        if self.enabled and self.r_prev is not None:
            dr = r - self.r_prev
            denom = self.interface.dot(dr, dr)
            if denom > 0:
                self.omega = float(np.clip(-self.omega * self.interface.dot(self.r_prev, dr) / denom,
                                           *self.bounds))
        self.r_prev = r
        scale = max(self.interface.norm(target), 1e-300)
        return current + self.omega * r, self.interface.norm(r) / scale
