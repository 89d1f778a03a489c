"""Staggered (Schwarz-type) DE x FE coupling for quasi-static 2D/3D problems (DESIGN main loop).

One coupled solve iterates:

1. ghost particles follow the FE fields at their centroids: ``Q^ = N D`` (seed 001 eq. 74-78);
2. the particle subproblem is solved with the ghosts prescribed;
3. free-particle motion is projected onto the prescribed FE dofs of the overlap,
   ``D^ = M^-1 N^^T (Q - N_D D)`` (eq. 79-90);
4. the FE problem is solved (SNES) with ``D^`` as Dirichlet values;

until the relative change of ``D^`` and of the ghost motion falls below ``tol``. Aitken's
dynamic relaxation (Kuettler & Wall 2008) accelerates the fixed point on ``D^``. Each
iteration's interface residual is logged in :attr:`StaggeredCoupling.history`. A solve that
does not converge raises :class:`InterfaceDidNotConverge` after restoring the last
converged FE state.

The particle side is any object with ``solve(u_ghost, theta_ghost) -> (u, theta)`` for all
particles (``u`` (n, dim), ``theta`` (n,) in 2D or (n, 3) in 3D), e.g.
:class:`dem.bonded.BondedSubproblem`. It is replicated on every rank (identical inputs give
identical outputs), while the FE side and the operators are distributed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Protocol

import dolfinx_solver  # noqa: F401

import numpy as np
from dolfinx import fem
from mpi4py import MPI

from coupling.locate import owner_ranks
from coupling.operators import FieldBasis, NodalProjection
from coupling.regions import CouplingRegions

__all__ = ["StaggeredOptions", "StaggeredCoupling", "InterfaceDidNotConverge", "ParticleSubproblem"]


class InterfaceDidNotConverge(RuntimeError):
    """The staggered iteration did not reach its tolerance; the message gives the history."""


class ParticleSubproblem(Protocol):
    def solve(self, u_ghost: np.ndarray, theta_ghost: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


@dataclass(frozen=True)
class StaggeredOptions:
    """Tolerances of the staggered loop.

    Attributes:
        tol: relative change of the interface values (D^ and ghost motion) to stop.
        max_iterations: iterations before :class:`InterfaceDidNotConverge`.
        aitken: Aitken dynamic relaxation on D^ (else fixed relaxation ``omega``).
        omega: first (or fixed) relaxation factor in (0, 1].
        regularization: of the nodal projection (0: plain L2 projection).
    """

    tol: float = 1e-10
    max_iterations: int = 200
    aitken: bool = True
    omega: float = 1.0
    regularization: float = 0.0

    def __post_init__(self):
        if not (0 < self.tol < 1):
            raise ValueError(f"tol must lie in (0, 1), got {self.tol!r}")
        if not (isinstance(self.max_iterations, int) and self.max_iterations >= 1):
            raise ValueError(f"max_iterations must be a positive integer, got {self.max_iterations!r}")
        if not (0 < self.omega <= 1):
            raise ValueError(f"omega must lie in (0, 1], got {self.omega!r}")


@dataclass
class _Field:
    sub: int
    ghost: FieldBasis
    free: FieldBasis
    projection: NodalProjection
    prescribed: np.ndarray  # owned local parent dofs


@dataclass
class StaggeredCoupling:
    """Couples a :class:`granfe.problem.MicropolarProblem` and a particle subproblem.

    Args:
        problem: the FE problem (its boundary conditions and loads stay in force).
        x: particle centroids (n, 3) [m], every particle of the subproblem, same on all ranks.
        kinds: (n,) 0 = free, 1 = ghost (from :meth:`CouplingRegions.particle_kinds`).
        particles: the particle subproblem (ghosts = particles with kind 1, in index order).
        regions: gives the prescribed FE nodes (B^h~).
        options: :class:`StaggeredOptions`.
    """

    problem: object
    x: np.ndarray
    kinds: np.ndarray
    particles: ParticleSubproblem
    regions: CouplingRegions
    options: StaggeredOptions = field(default_factory=StaggeredOptions)

    def __post_init__(self):
        problem = self.problem
        V, domain = problem.V, problem.domain
        comm = self.comm = domain.comm
        gdim = self.gdim = domain.geometry.dim
        self.x = np.asarray(self.x, dtype=float)
        self.kinds = np.asarray(self.kinds)
        if np.any((self.kinds != 0) & (self.kinds != 1)):
            raise ValueError("kinds must be 0 (free) or 1 (ghost); drop particles outside the "
                             "coupled region before coupling")
        t0 = time.perf_counter()
        owners = owner_ranks(domain, self.x[:, :gdim])
        mine = owners == comm.rank
        self.ghost_index = np.flatnonzero(self.kinds == 1)
        self.free_index = np.flatnonzero(self.kinds == 0)
        self._ghost_mine = np.flatnonzero(mine[self.ghost_index])  # positions within ghost list
        self._free_mine = self.free_index[mine[self.free_index]]    # particle indices
        ghost_pts = self.x[self.ghost_index[self._ghost_mine], :gdim]
        free_pts = self.x[self._free_mine, :gdim]
        self.g = fem.Function(V, name="prescribed_values")
        bc_dofs, self.fields = [], []
        for sub in (0, 1):
            ghost = FieldBasis.build(V, ghost_pts, sub=sub)
            free = FieldBasis.build(V, free_pts, sub=sub)
            Vc, parent = V.sub(sub).collapse()
            parent = np.asarray(parent[0] if isinstance(parent, list) else parent, dtype=np.int64)
            bs = Vc.dofmap.bs
            coords = np.repeat(Vc.tabulate_dof_coordinates(), bs, axis=0)[: parent.size]
            local = parent[self.regions.prescribed_nodes(coords[:, :gdim])]
            owned = local[local < V.dofmap.index_map.size_local * V.dofmap.index_map_bs]
            projection = NodalProjection(free, owned, self.options.regularization)
            self.fields.append(_Field(sub, ghost, free, projection, np.sort(owned)))
            bc_dofs.append(local)
        dofs = np.unique(np.concatenate(bc_dofs)).astype(np.int32)
        self.n_prescribed = comm.allreduce(sum(f.prescribed.size for f in self.fields))
        if self.n_prescribed == 0:
            raise ValueError("no FE dofs are prescribed: the window is smaller than the "
                             "handshake depth or the mesh has no nodes inside it")
        problem.bcs.append(fem.dirichletbc(self.g, dofs))
        # the FE problem is linear and only the Dirichlet values change between iterations:
        # factorise the Jacobian once and reuse it for every FE solve of the loop
        problem.petsc_options.setdefault("snes_lag_jacobian", -2)
        problem.petsc_options.setdefault("snes_lag_jacobian_persists", True)
        problem._snes = None
        self.history: list[dict] = []
        self.timings = {"operators": time.perf_counter() - t0, "particles": 0.0, "fe": 0.0,
                        "projection": 0.0}

    # ------------------------------------------------------------------------------------
    def _norm(self, v):
        return np.sqrt(self.comm.allreduce(float(v @ v), MPI.SUM))

    def _ghost_motion(self):
        """(u_ghost (n_g, dim), theta_ghost) on every rank, from the FE fields."""
        w = self.problem.w
        out = []
        for f in self.fields:
            local = f.ghost.interpolate(w)
            parts = self.comm.allgather((self._ghost_mine, local))
            values = np.zeros((len(self.ghost_index), local.shape[1] if local.ndim > 1 else 1))
            for idx, val in parts:
                values[idx] = val.reshape(len(idx), -1)
            out.append(values)
        u, theta = out
        return u, (theta[:, 0] if self.gdim == 2 else theta)

    def _project(self, u, theta):
        w = self.problem.w
        th = theta.reshape(len(theta), -1)
        return [f.projection.project(q[self._free_mine], w)
                for f, q in zip(self.fields, (u[:, : self.gdim], th))]

    def _set_prescribed(self, values):
        for f, v in zip(self.fields, values):
            self.g.x.array[f.prescribed] = v
        self.g.x.scatter_forward()

    def solve(self) -> int:
        """Iterate to a coupled equilibrium; returns the number of iterations."""
        opts = self.options
        state0 = self.problem.w.x.array.copy()
        current = [self.g.x.array[f.prescribed].copy() for f in self.fields]
        r_prev, omega = None, opts.omega
        ghost_prev = None
        for it in range(1, opts.max_iterations + 1):
            t0 = time.perf_counter()
            u_g, th_g = self._ghost_motion()
            self.u, self.theta = self.particles.solve(u_g, th_g)
            t1 = time.perf_counter()
            target = self._project(self.u, self.theta)
            t2 = time.perf_counter()
            r = np.concatenate([t - c for t, c in zip(target, current)])
            scale = max(self._norm(np.concatenate(target)), 1e-300)
            if opts.aitken and r_prev is not None:
                dr = r - r_prev
                denom = self.comm.allreduce(float(dr @ dr), MPI.SUM)
                if denom > 0:
                    omega = -omega * self.comm.allreduce(float(r_prev @ dr), MPI.SUM) / denom
                    omega = float(np.clip(omega, 0.05, 2.0))
            sizes = np.cumsum([len(c) for c in current])[:-1]
            current = [c + omega * dc for c, dc in zip(current, np.split(r, sizes))]
            self._set_prescribed(current)
            try:
                self.problem.solve()
            except Exception:
                self.problem.w.x.array[:] = state0
                raise
            t3 = time.perf_counter()
            g_all = np.concatenate([u_g.ravel(), np.ravel(th_g)])
            dg = (np.linalg.norm(g_all - ghost_prev) / max(np.linalg.norm(g_all), 1e-300)
                  if ghost_prev is not None else 1.0)
            ghost_prev = g_all
            res = self._norm(r) / scale
            self.history.append({"iteration": it, "interface_residual": res,
                                 "ghost_change": float(dg), "omega": omega})
            self.timings["particles"] += t1 - t0
            self.timings["projection"] += t2 - t1
            self.timings["fe"] += t3 - t2
            r_prev = r
            if res < opts.tol and dg < max(opts.tol, 1e-14) * 10:
                return it
            if not np.isfinite(res):
                break
        self.problem.w.x.array[:] = state0
        tail = ", ".join(f"{h['interface_residual']:.2e}" for h in self.history[-5:])
        raise InterfaceDidNotConverge(
            f"staggered DE x FE iteration did not converge in {it} iterations "
            f"(tol {opts.tol:g}); last interface residuals: {tail}. The FE state before this "
            f"solve was restored; try a wider overlap (handshake), more iterations or omega < 1"
        )
