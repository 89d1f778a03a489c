"""The DE x FE interface: ghost motion from the FE fields, prescribed FE dofs from the
particles, and the accelerators of the fixed point on the exchanged values (used by the static
and the dynamic staggered solvers): constant relaxation, Aitken's dynamic relaxation and the
interface quasi-Newton method IQN-ILS.

Every accelerator has the same contract: ``update(current, target) -> (new, relative
residual)`` for one evaluation ``target = H(current)`` of the fixed-point map, ``new_step()``
at a time (load) step boundary and ``reset()`` to forget everything. They see the
distributed interface vector (each rank its owned entries) only through the ``dot`` / ``norm``
of the space they are given (:class:`CouplingInterface`): global reductions, so every rank
takes the same decisions and coefficients.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import scipy.linalg
from dolfinx import fem

from coupling.locate import owner_ranks, relocate
from coupling.micro_kinematics import MicroDeformationFit, axial_vector, micro_deformation
from coupling.operators import FieldBasis, NodalProjection
from coupling.regions import CouplingRegions

__all__ = ["CouplingInterface", "DistributedVectors", "ConstantRelaxation", "Aitken", "IQNOptions",
           "IQNILS"]


class DistributedVectors:
    """The global Euclidean inner product of vectors whose entries are split over the ranks of
    ``comm`` (each rank holds its owned entries, none twice): every rank gets the same value.

    Args:
        comm: the communicator the entries are split over.
    """

    def __init__(self, comm):
        self.comm = comm

    def norm(self, v: np.ndarray) -> float:
        return float(np.sqrt(self.comm.allreduce(float(v @ v), MPI.SUM)))

    def dot(self, a: np.ndarray, b: np.ndarray) -> float:
        return float(self.comm.allreduce(float(a @ b), MPI.SUM))

    def dots(self, vectors: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Global inner products (m,) of the rows of ``vectors`` (m, n_local) with ``b``
        (n_local,) in one reduction (m calls of :meth:`dot` would take m)."""
        local = np.ascontiguousarray(np.asarray(vectors, dtype=float).reshape(-1, len(b)) @ b)
        out = np.empty_like(local)
        if local.size:
            self.comm.Allreduce(local, out, op=MPI.SUM)
        return out


@dataclass
class _Field:
    sub: int
    ghost: FieldBasis
    free: FieldBasis
    projection: NodalProjection | None   # None: a micro-deformation, fitted (self.micro)
    prescribed: np.ndarray  # owned local parent dofs


class CouplingInterface(DistributedVectors):
    """Operators between a continuum FE problem and a set of particles; the prescribed values
    (this rank's owned dofs) are :class:`DistributedVectors` over the mesh's communicator.

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
        micro_fit: options of :class:`coupling.micro_kinematics.MicroDeformationFit`
            (``min_grains``, ``min_spread``) for a micromorphic model.

    A micromorphic model (``phi = chi - I`` of shape (gdim, gdim), :func:`coupling.
    micro_kinematics.micro_deformation`) has its prescribed phi fitted to the free grains'
    displacements (:attr:`micro`, no projection of their spins) and gives its ghosts the
    rotation ``axial(skew(phi))``; a micropolar one projects and returns its rotation phi.
    """

    def __init__(self, problem, x, kinds, regions: CouplingRegions, regularization: float = 0.0,
                 min_support: float = 0.0, micro_fit: dict | None = None):
        self.problem = problem
        V, domain = problem.V, problem.domain
        super().__init__(domain.comm)
        comm = self.comm
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
        self.micro = None   # the micro-deformation fit of a micromorphic model's phi
        fitted = self.coupled_fields(problem)[1] if micro_deformation(problem) else -1
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
            if sub == fitted:
                projection = None
                self.micro = MicroDeformationFit(free, self._free_points(self.x), owned, **(micro_fit or {}))
            else:
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
        #: the prescribed dofs' condition in ``problem.bcs`` (a fresh interface of the same
        #: problem takes this one's out first)
        self.bc = fem.dirichletbc(self.g, dofs)
        problem.bcs.append(self.bc)
        # a linear FE problem whose Dirichlet values alone change between solves: factorise
        # the Jacobian once and reuse it (not for a model with state: a plastic one's
        # Jacobian changes, and a lagged one makes Newton converge linearly)
        if problem.model.linear and not problem.state:
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
                if f.projection is not None:
                    f.projection = NodalProjection(f.free, f.prescribed, self.regularization)
        else:
            for f in self.fields:
                n_ghost = f.ghost.update(self._ghost_points(x), located[0])
                n_free = f.free.update(self._free_points(x), located[1])
                if f.projection is not None:
                    counts["pattern_rebuilt"] |= f.projection.update()
            counts["changed_cell"] = n_ghost + n_free
        if self.micro is not None:
            self.micro.update(self.fields[1].free, self._free_points(x))
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

    def ghost_motion(self, w: fem.Function | None = None):
        """(u_ghost (n_g, dim), theta_ghost (n_g,) or (n_g, 3)) on every rank: ``Q^ = N D``;
        a micromorphic model's theta is the axial vector of skew(phi) at the ghosts (a rigid
        grain carries only the rotation part of its micro-element's motion,
        :func:`coupling.micro_kinematics.axial_vector`)."""
        w = self.problem.w if w is None else w
        u, theta = (gather_rows(self.comm, f.ghost.interpolate(w), self._ghost_mine, len(self.ghost_index))
                    for f in self.fields)
        if self.micro is not None:
            return u, axial_vector(theta, self.gdim)
        return u, (theta[:, 0] if self.gdim == 2 else theta)

    def project(self, u: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Prescribed-dof values (this rank's, u then phi) from all particles' motion (a
        micromorphic phi: fitted to the displacements u, theta unused)."""
        w = self.problem.w
        if self.micro is not None:
            return np.concatenate([self.project_displacement(u), self.project_micro_deformation(u)])
        th = np.reshape(theta, (len(theta), -1))
        return np.concatenate([f.projection.project(q[self._free_mine], w)
                               for f, q in zip(self.fields, (u[:, : self.gdim], th), strict=False)])

    def project_micro_deformation(self, u: np.ndarray) -> np.ndarray:
        """A micromorphic model's prescribed phi dofs (this rank's, in the order of
        ``fields[1].prescribed``): the least-squares fit of the free grains' displacements
        ``u`` (n, >= dim) of all particles about each node (:class:`coupling.micro_kinematics.
        MicroDeformationFit`). Collective."""
        if self.micro is None:
            raise ValueError(f"the {self.problem.model.name} model's phi is a rotation, not a "
                             "micro-deformation: nothing to fit")
        return self.micro.fit(np.asarray(u)[self._free_mine, : self.gdim])

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


def gather_rows(comm, local: np.ndarray, mine: np.ndarray, n: int) -> np.ndarray:
    """Rows (n, k) on every rank from each rank's rows ``local`` (m, k) at positions ``mine``."""
    k = local.shape[1]
    out = np.zeros((n, k))
    for idx, val in comm.allgather((mine, local)):
        out[idx] = val.reshape(len(idx), k)
    return out


class ConstantRelaxation:
    """Fixed relaxation ``x <- x + omega (H(x) - x)`` (Gauss-Seidel for ``omega = 1``).

    Args:
        space: gives ``norm`` of the distributed interface vector (a :class:`CouplingInterface`).
        omega: the relaxation factor.
    """

    def __init__(self, space, omega: float = 1.0):
        self.space, self.omega = space, float(omega)
        self.columns = 0

    def reset(self) -> None:
        """Nothing to forget."""

    def new_step(self) -> None:
        """Nothing to forget."""

    def update(self, current: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, float]:
        """New iterate and the relative residual ``|H(x) - x| / |H(x)|``."""
        r = target - current
        return current + self.omega * r, self.space.norm(r) / max(self.space.norm(target), 1e-300)


class Aitken:
    """Aitken's dynamic relaxation of a fixed point ``x <- x + omega (T(x) - x)``."""

    columns = 0

    def __init__(self, interface: CouplingInterface, omega: float = 1.0, bounds=(0.05, 2.0)):
        self.interface, self.omega0, self.bounds = interface, omega, bounds
        self.reset()

    def reset(self):
        self.omega, self.r_prev = self.omega0, None

    def new_step(self) -> None:
        """A new time (load) step starts again from the first relaxation factor."""
        self.reset()

    def update(self, current: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, float]:
        """New iterate and the relative residual ``|T(x) - x| / |T(x)|``."""
        r = target - current
        if self.r_prev is not None:
            dr = r - self.r_prev
            denom = self.interface.dot(dr, dr)
            if denom > 0:
                self.omega = float(np.clip(-self.omega * self.interface.dot(self.r_prev, dr) / denom,
                                           *self.bounds))
        self.r_prev = r
        scale = max(self.interface.norm(target), 1e-300)
        return current + self.omega * r, self.interface.norm(r) / scale


@dataclass(frozen=True)
class IQNOptions:
    """Settings of :class:`IQNILS` (the names of preCICE's IQN-ILS options in brackets).

    Attributes:
        reuse: time (load) steps whose secant pairs stay in the least-squares problem of the
            following steps [time-windows-reused]; 0: each step starts with the relaxation
            ``omega``, then learns from its own iterations only.
        max_columns: most secant pairs kept, newest first [max-used-iterations]; the oldest
            are dropped beyond it.
        filter_limit: QR2 filter [filter limit]: a pair whose residual difference has less than
            this fraction of its norm outside the span of the newer ones is nearly linearly
            dependent on them and is dropped for good (the least-squares problem would be
            ill-conditioned); 0 keeps every pair that is not exactly dependent.
    """

    reuse: int = 0
    max_columns: int = 100
    filter_limit: float = 1e-8

    def __post_init__(self):
        if not (isinstance(self.reuse, int) and self.reuse >= 0):
            raise ValueError(f"iqn.reuse (time steps whose secant pairs are reused) must be an integer "
                             f">= 0, got {self.reuse!r}")
        if not (isinstance(self.max_columns, int) and self.max_columns >= 1):
            raise ValueError(f"iqn.max_columns must be a positive integer, got {self.max_columns!r}")
        if not (0 <= self.filter_limit < 1):
            raise ValueError(f"iqn.filter_limit (QR2 filter) must lie in [0, 1), got {self.filter_limit!r}")


class IQNILS:
    """Interface quasi-Newton with an inverse Jacobian from a least-squares model (IQN-ILS,
    Degroote, Bathe & Vierendeels 2009, as preCICE uses for partitioned coupling).

    For the fixed point ``x = H(x)`` with residual ``r = H(x) - x``, the k-th update keeps the
    differences between consecutive iterations (newest first) of the residuals,
    ``V = [r^k - r^(k-1), ...]``, and of the outputs, ``W = [H(x^k) - H(x^(k-1)), ...]``,
    solves ``min_c |V c + r^k|`` and steps to ``x^(k+1) = H(x^k) + W c``. The first
    iteration without pairs relaxes, ``x + omega r``. On a linear map ``H(x) = A x + b`` of
    dimension n, ``x^k + (x^k - x^(k-1), ...) c`` is the GMRES iterate of ``(I - A) x = b``
    over the k pairs' Krylov space and ``x^(k+1)`` is H of it (any spectrum without the
    eigenvalue 1, also where plain iteration diverges): the (n + 1)-th update returns the
    solution, and the (n + 2)-th evaluation of H confirms it.

    The least-squares problem is solved by a QR factorisation of V, rebuilt newest column
    first by classical Gram-Schmidt with one re-orthogonalisation ("twice is enough"), every
    inner product a global one (``space.dots`` / ``space.dot``): each rank holds its rows of
    Q, and R and ``Q^T r`` are the same on every rank, as a Krylov solver's norms are. The QR2
    filter drops older pairs that the newer ones nearly span (:class:`IQNOptions`). Cost per
    update with m pairs: 2m + 1 reductions of at most m numbers, O(m^2 n) flops on the local
    rows and 2m stored vectors.

    Args:
        space: ``dot(a, b)`` and ``norm(a)`` of the distributed interface vector, and
            optionally ``dots(Q, b)``, the m inner products of Q's rows with b in one reduction
            (a :class:`CouplingInterface` has all three).
        omega: relaxation of the first iteration, in (0, 1].
        options: :class:`IQNOptions`.
    """

    def __init__(self, space, omega: float = 1.0, options: IQNOptions = IQNOptions()):
        if not 0 < omega <= 1:
            raise ValueError(f"omega (initial relaxation of IQN-ILS) must lie in (0, 1], got {omega!r}")
        self.space, self.omega, self.options = space, float(omega), options
        self.reset()

    def reset(self) -> None:
        """Forget every pair (a new problem)."""
        self._pairs: list[tuple[np.ndarray, np.ndarray, int]] = []   # (dr, dH, step), newest first
        self._step = 0
        self._last = None           # (r, H(x)) of the last update of this step
        self.columns = 0            # pairs used by the last update
        self.coefficients = np.zeros(0)   # c of the last update (the same on every rank)
        self.filtered = 0           # pairs dropped by the filter, all steps

    def new_step(self) -> None:
        """A new time (load) step: no difference spans the step boundary; the pairs of the last
        ``options.reuse`` steps are kept."""
        self._step += 1
        self._last = None
        self._pairs = [p for p in self._pairs if p[2] >= self._step - self.options.reuse]

    def state_dict(self) -> dict:
        """What the next steps reuse, at a step boundary (after the last update of a step):
        this rank's rows of the kept pairs ``dr`` and ``dh`` (m, n_local), the step of each
        (m,), the step count and the filter's count; copies, ``np.savez``-ready. A restart on
        the same partition that loads it continues exactly."""
        n = len(self._pairs[0][0]) if self._pairs else 0
        m = len(self._pairs)   # a rank may hold no interface entries (n = 0) and still m pairs
        return {"dr": np.array([p[0] for p in self._pairs], dtype=float).reshape(m, n),
                "dh": np.array([p[1] for p in self._pairs], dtype=float).reshape(m, n),
                "pair_step": np.array([p[2] for p in self._pairs], dtype=np.int64),
                "step": np.int64(self._step), "filtered": np.int64(self.filtered)}

    def load_state(self, d) -> None:
        """Restore :meth:`state_dict` (a dict or an ``np.load`` of one); ValueError naming an
        entry that is missing or does not fit."""
        missing = [k for k in ("dr", "dh", "pair_step", "step", "filtered") if k not in d]
        if missing:
            raise ValueError(f"IQN-ILS state has no {missing} (not an IQNILS.state_dict?)")
        dr, dh, steps = np.asarray(d["dr"], float), np.asarray(d["dh"], float), np.asarray(d["pair_step"])
        if dr.shape != dh.shape or dr.ndim != 2 or len(steps) != len(dr):
            raise ValueError(f"IQN-ILS state: 'dr' {dr.shape}, 'dh' {dh.shape} and 'pair_step' "
                             f"{steps.shape} do not fit together")
        self.reset()
        self._pairs = [(a.copy(), b.copy(), int(k)) for a, b, k in zip(dr, dh, steps, strict=True)]
        self._step, self.filtered = int(d["step"]), int(d["filtered"])

    def update(self, current: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, float]:
        """New iterate and the relative residual ``|H(x) - x| / |H(x)|`` for ``target = H(current)``."""
        space = self.space
        r = target - current
        res = space.norm(r) / max(space.norm(target), 1e-300)
        if self._last is not None:
            self._pairs.insert(0, (r - self._last[0], target - self._last[1], self._step))
            del self._pairs[self.options.max_columns:]
        self._last = (r, np.array(target, dtype=float, copy=True))
        if not np.isfinite(res):
            self.columns, self.coefficients = 0, np.zeros(0)
            return current + self.omega * r, res
        Q, R, kept = self._factorise([p[0] for p in self._pairs])
        self.filtered += len(self._pairs) - len(kept)
        self._pairs = [self._pairs[j] for j in kept]
        self.columns = len(kept)
        if not kept:
            self.coefficients = np.zeros(0)
            return current + self.omega * r, res
        self.coefficients = c = scipy.linalg.solve_triangular(R, -self._dots(Q, r))
        new = np.array(target, dtype=float, copy=True)
        for cj, (_, dw, _) in zip(c, self._pairs, strict=True):
            new += cj * dw
        return new, res

    def _factorise(self, columns: list[np.ndarray]):
        """QR of the columns (local rows), newest first, with the QR2 filter: (Q (m, n_local),
        R (m, m) upper triangular, indices of the columns kept)."""
        space, limit = self.space, self.options.filter_limit
        n_local = len(columns[0]) if columns else 0
        Q = np.zeros((0, n_local))
        R_cols, kept = [], []
        for j, v in enumerate(columns):
            rho0 = space.norm(v)
            if not (np.isfinite(rho0) and rho0 > 0):
                continue
            w, coeff = np.array(v, dtype=float, copy=True), np.zeros(len(Q))
            for _ in range(2):
                s = self._dots(Q, w)
                w -= s @ Q
                coeff += s
            rho = space.norm(w)
            if not rho > max(limit, 1e-14) * rho0:
                continue
            Q = np.vstack([Q, w / rho])
            R_cols.append(np.append(coeff, rho))
            kept.append(j)
        R = np.zeros((len(Q), len(Q)))
        for j, col in enumerate(R_cols):
            R[: j + 1, j] = col
        return Q, R, kept

    def _dots(self, Q: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Global ``Q w``: one reduction if the space has ``dots``, else one per row."""
        dots = getattr(self.space, "dots", None)
        if dots is not None:
            return dots(Q, w)
        return np.array([self.space.dot(q, w) for q in Q])
