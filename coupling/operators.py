"""Interpolation and projection operators between FE dofs and particle centroids.

``N`` evaluates the FE basis of one field (a sub-space of a mixed space: u or phi) at the
particle centroids, seed 001 eq. 74-78: ``Q = N D``. It is a distributed PETSc matrix with
one row per particle component (rows owned by the rank owning the particle's cell) and one
column per dof of the *parent* space (its global numbering), so it acts directly on
``Function.x.petsc_vec`` of the mixed solution.

``NodalProjection`` is the discrete L2 projection of particle motion onto the prescribed
nodes of the overlap, seed 001 eq. 79-90: ``D^ = M^-1 N^^T (Q - N_D D)`` with
``M = N^^T N^`` where ``N^`` holds the columns of the prescribed dofs.

When particles move, ``FieldBasis.update`` and ``NodalProjection.update`` re-locate only the
particles that left their cell and refill N (and M's values, refactorised numerically) in
place; sparsity and symbolic factorisation are rebuilt only if some particle changed cell.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import dolfinx_solver  # noqa: F401  (orders MPI before the dolfinx bindings)
from petsc4py import PETSc

import dolfinx.fem
import dolfinx.la
import numpy as np
import scipy.sparse as sp

from coupling.locate import PointsOutsideMesh, locate_owned, pad_points, relocate

__all__ = ["FieldBasis", "NodalProjection", "SingularProjection"]


class SingularProjection(ValueError):
    """The projection matrix M is singular: named dofs have too few particles in their support."""


class _FieldLayout:
    """What a basis needs of one field of V: collapsed space, parent dofs, scalar element and
    the global column of every local parent dof."""

    def __init__(self, V: dolfinx.fem.FunctionSpace, sub: int | None):
        if sub is None:      # a plain (not mixed) space is its own collapsed space
            self.Vc = V
            imap = V.dofmap.index_map
            self.parent = np.arange((imap.size_local + imap.num_ghosts) * V.dofmap.bs, dtype=np.int64)
        else:
            self.Vc, parent = V.sub(sub).collapse()
            self.parent = np.asarray(parent[0] if isinstance(parent, list) else parent, dtype=np.int64)
        if self.Vc.element.needs_dof_transformations:
            raise NotImplementedError(
                "FieldBasis supports elements without dof transformations (Lagrange up to P2)"
            )
        ufl_el = self.Vc.ufl_element()
        self.scalar = (ufl_el.sub_elements[0] if ufl_el.block_size > 1 else ufl_el).basix_element
        self.bs = self.Vc.dofmap.bs
        imap, bsV = V.dofmap.index_map, V.dofmap.bs
        self.n_parent_local = (imap.size_local + imap.num_ghosts) * bsV
        blocks = np.arange(self.n_parent_local) // bsV
        self.global_cols = imap.local_to_global(blocks.astype(np.int32)) * bsV + np.arange(
            self.n_parent_local
        ) % bsV
        self._pattern = None  # (cells, order, indptr, indices, global indices) of the last rows
        self._last = None     # (indices of the last rows returned, their global indices)

    def rows(self, cells: np.ndarray, X: np.ndarray) -> sp.csr_matrix:
        """Owned rows ``p * bs + k`` over the local parent dofs for points in cells at X.

        A row holds the ``nd`` distinct dofs of its cell, columns ascending. The pattern
        (which entry goes where) depends on the cells alone: it is kept while they stay the
        same, so a particle that moves inside its cell costs a tabulation and a gather (the
        pore fluid re-evaluates three bases every fluid step)."""
        bs, n = self.bs, len(cells)
        if n == 0:
            return sp.csr_matrix((0, self.n_parent_local))
        phi = self.scalar.tabulate(0, X)[0, :, :, 0]  # (n, ndofs)
        vals = np.repeat(phi[:, None, :], bs, axis=1).ravel()
        if self._pattern is None or not np.array_equal(self._pattern[0], cells):
            cdofs = self.Vc.dofmap.list[cells]  # (n, ndofs)
            nd = cdofs.shape[1]
            rows = np.repeat(np.arange(n * bs), nd)
            cols = self.parent[(cdofs[:, None, :] * bs + np.arange(bs)[None, :, None])].ravel()
            order = np.lexsort((cols, rows))
            indices = cols[order]
            self._pattern = (np.array(cells, copy=True), order, np.arange(0, n * bs * nd + 1, nd),
                             indices, self.global_cols[indices].astype(PETSc.IntType))
        _, order, indptr, indices, global_indices = self._pattern
        local = sp.csr_matrix((vals[order], indices, indptr), shape=(n * bs, self.n_parent_local))
        self._last = (local.indices, global_indices)   # (scipy may have cast the indices)
        return local

    def csr(self, local: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(indptr, global columns, values) of the owned rows, as PETSc takes them."""
        if self._last is not None and local.indices is self._last[0]:
            cols = self._last[1]
        else:
            cols = self.global_cols[local.indices].astype(PETSc.IntType)
        return local.indptr.astype(PETSc.IntType), cols, local.data


@dataclass
class FieldBasis:
    """Basis functions of one field of ``V`` evaluated at particle centroids.

    Attributes:
        V: the (mixed) parent function space.
        sub: index of the field in ``V`` (``None``: ``V`` itself).
        value_size: components per particle (e.g. gdim for u, 1 for phi_z in 2D).
        matrix: PETSc Mat (n_particles * value_size, dim V), rows ``p * value_size + k``.
        local: the owned rows as scipy CSR over the local (owned + ghost) parent dofs.
        dofs: local parent dof indices this field uses (owned and ghost), sorted.
        dof_coordinates: (len(dofs), 3) coordinates of those dofs [m].
        particle_offset: global index of this rank's first particle.
        cells: (n,) owned local cell of each particle (kept for :meth:`update`).
        pattern_version: increases whenever :attr:`matrix` is rebuilt with a new sparsity.
    """

    V: dolfinx.fem.FunctionSpace
    sub: int | None
    value_size: int
    matrix: PETSc.Mat
    local: sp.csr_matrix
    dofs: np.ndarray
    dof_coordinates: np.ndarray
    particle_offset: int
    cells: np.ndarray | None = None
    pattern_version: int = 0
    _layout: _FieldLayout | None = field(default=None, repr=False)

    @classmethod
    def build(
        cls, V: dolfinx.fem.FunctionSpace, points: np.ndarray, sub: int | None = None
    ) -> FieldBasis:
        """Evaluate the field's basis at ``points`` (n, gdim) held by their owning rank.

        Collective (collapses the sub-space, builds a distributed matrix). Raises
        :class:`coupling.locate.PointsOutsideMesh` for points not in an owned cell.
        """
        mesh = V.mesh
        comm = mesh.comm
        x = pad_points(points)
        cells, X = locate_owned(mesh, x)
        f = _FieldLayout(V, sub)
        n_local = x.shape[0]
        offset = comm.exscan(n_local) or 0
        local = f.rows(cells, X)
        A = cls._matrix(V, f, local)

        dofs = np.unique(f.parent)
        coords_c = f.Vc.tabulate_dof_coordinates()
        dof_coordinates = np.empty((dofs.size, 3))
        dof_coordinates[np.searchsorted(dofs, f.parent)] = np.repeat(coords_c, f.bs, axis=0)[
            : f.parent.size
        ]
        return cls(V, sub, f.bs, A, local, dofs, dof_coordinates, offset, cells, 0, f)

    @staticmethod
    def _matrix(V, f: _FieldLayout, local: sp.csr_matrix) -> PETSc.Mat:
        comm = V.mesh.comm
        n_rows = local.shape[0]
        imap, bsV = V.dofmap.index_map, V.dofmap.bs
        n_dofs_owned, n_dofs_global = imap.size_local * bsV, imap.size_global * bsV
        # exact preallocation from the rows themselves (PETSc numbers them from this rank's
        # first row): a changed sparsity is a new matrix, an unchanged one is refilled in place
        A = PETSc.Mat().createAIJ(
            ((n_rows, comm.allreduce(n_rows)), (n_dofs_owned, n_dofs_global)),
            csr=f.csr(local),
            comm=comm,
        )
        A.assemble()
        return A

    def update(self, points: np.ndarray, located=None) -> int:
        """Move this rank's particles to ``points`` (n, gdim), same particles and order.

        Re-locates only the particles that left their cell (:func:`coupling.locate.relocate`),
        re-evaluates every row, and keeps the matrix (same sparsity, values overwritten) unless
        some particle on some rank changed cell, when it is rebuilt. ``located`` = (cells, X,
        changed) from a shared :func:`relocate` call saves the search for a second field.
        Collective. Returns the number of particles (all ranks) that changed cell; raises
        :class:`coupling.locate.PointsOutsideMesh` on every rank if some left their rank's cells.
        """
        comm = self.V.mesh.comm
        x = pad_points(points)
        if x.shape[0] != len(self.cells):
            raise ValueError(f"update needs the same {len(self.cells)} particles, got {x.shape[0]}")
        if located is None:
            cells, X, changed, lost = relocate(self.V.mesh, x, self.cells)
            n_lost = comm.allreduce(int(lost.sum()))
            if n_lost:
                raise PointsOutsideMesh(
                    f"{n_lost} particle(s) left the cells of their rank: redistribute and "
                    "build anew"
                )
        else:
            cells, X, changed = located
        n_changed = comm.allreduce(int(np.count_nonzero(changed)))
        local = self._layout.rows(cells, X)
        if n_changed == 0:
            self.matrix.setValuesCSR(*self._layout.csr(local))
            self.matrix.assemble()
        else:
            self.matrix.destroy()
            self.matrix = self._matrix(self.V, self._layout, local)
            self.pattern_version += 1
        self.local, self.cells = local, np.asarray(cells, dtype=np.int32)
        return n_changed

    def interpolate(self, u: dolfinx.fem.Function) -> np.ndarray:
        """Field values at this rank's particles, (n, value_size): ``Q = N D`` (eq. 74)."""
        u.x.scatter_forward()
        q = self.local @ u.x.array
        return q.reshape(-1, self.value_size)

    def global_dofs(self, local_dofs: np.ndarray) -> np.ndarray:
        """Global indices of local parent dofs (owned or ghost)."""
        imap, bs = self.V.dofmap.index_map, self.V.dofmap.bs
        local_dofs = np.asarray(local_dofs, dtype=np.int64)
        return imap.local_to_global((local_dofs // bs).astype(np.int32)) * bs + local_dofs % bs


class NodalProjection:
    """Discrete L2 projection of particle values onto prescribed FE dofs (seed 001 eq. 79-90).

    ``D^ = argmin |N^ D^ - (Q - N_D D)|^2``, i.e. ``M D^ = N^^T (Q - N_D D)`` with
    ``M = N^^T N^``. ``prescribed`` are local, *owned* parent dof indices of the field.
    M is factorised once (MUMPS); after particles move (:meth:`update`) only its values are
    refactorised, and its sparsity and symbolic factorisation are rebuilt only when some
    particle changed cell.

    Args:
        basis: the field's :class:`FieldBasis`.
        prescribed: owned local dof indices on this rank (may be empty on some ranks).
        regularization: 0 for the plain projection (singular M raises, naming the dofs), or
            ``eps > 0`` to solve ``(M + eps * mean(diag M) I) D^ = ...`` instead.
    """

    def __init__(self, basis: FieldBasis, prescribed: np.ndarray, regularization: float = 0.0):
        if not regularization >= 0.0:
            raise ValueError(f"regularization must be >= 0, got {regularization!r}")
        comm = basis.V.mesh.comm
        imap, bsV = basis.V.dofmap.index_map, basis.V.dofmap.bs
        prescribed = np.unique(np.asarray(prescribed, dtype=np.int64))
        if prescribed.size and prescribed.max() >= imap.size_local * bsV:
            raise ValueError("prescribed dofs must be owned local dofs of the parent space")
        if not np.all(np.isin(prescribed, basis.dofs)):
            raise ValueError("prescribed dofs must belong to the projected field")
        self.basis = basis
        self.prescribed = prescribed
        # ghost copies of prescribed dofs owned by other ranks must be excluded from N_D D too
        mask = dolfinx.la.vector(imap, bsV)
        mask.array[prescribed] = 1.0
        mask.scatter_forward()
        self._mask = mask.array > 0.5
        glob = basis.global_dofs(prescribed).astype(PETSc.IntType)
        self._cols = PETSc.IS().createGeneral(glob, comm=comm)
        self.regularization = regularization
        self.rebuilds = 0  # new sparsity: submatrix, product and symbolic factorisation anew
        self.value_updates = 0  # same sparsity: values recomputed, numeric refactorisation only
        self.N_hat = self.M = self.ksp = None
        self._assemble()

    def _assemble(self) -> None:
        """(Re)build N^ and M = N^^T N^ from the basis matrix; reuse their sparsity and the
        symbolic factorisation while the basis keeps its pattern. Collective."""
        basis, comm = self.basis, self.basis.V.mesh.comm
        reuse = self.M is not None and self._pattern == basis.pattern_version
        rlo, rhi = basis.matrix.getOwnershipRange()
        rows = PETSc.IS().createStride(rhi - rlo, first=rlo, step=1, comm=comm)
        if reuse:
            basis.matrix.createSubMatrix(rows, self._cols, submat=self.N_hat)
            self.N_hat.transposeMatMult(self.N_hat, result=self.M)
            self.value_updates += 1
        else:
            for obj in (self.N_hat, self.M, self.ksp):
                if obj is not None:
                    obj.destroy()
            self.N_hat = basis.matrix.createSubMatrix(rows, self._cols)
            self.M = self.N_hat.transposeMatMult(self.N_hat)
            self.rebuilds += 1
        self._pattern = basis.pattern_version
        diag = self.M.getDiagonal()
        d = diag.getArray().copy()
        scale = comm.allreduce(d.sum()) / max(comm.allreduce(d.size), 1)
        empty = np.flatnonzero(d <= 1e-14 * max(scale, 1e-300))
        prescribed = self.prescribed
        if self.regularization > 0.0:
            diag.set(self.regularization * scale)
            self.M.setDiagonal(diag, addv=PETSc.InsertMode.ADD_VALUES)
        elif comm.allreduce(empty.size):
            where = [
                np.array2string(basis.dof_coordinates[np.searchsorted(basis.dofs, prescribed[e])])
                for e in empty[:5]
            ]
            raise SingularProjection(
                f"{comm.allreduce(empty.size)} prescribed dof(s) have no particle in their "
                f"support, so M = N^T N is singular; on rank {comm.rank}: dofs "
                f"{prescribed[empty[:5]].tolist()} at {where}. Shrink the prescribed region, "
                f"add particles, or pass regularization > 0."
            )
        if reuse:
            self.ksp.setOperators(self.M)  # same pattern: numeric refactorisation at next solve
            return
        self.ksp = PETSc.KSP().create(comm)
        self.ksp.setOperators(self.M)
        self.ksp.setType("preonly")
        pc = self.ksp.getPC()
        pc.setType("cholesky")
        pc.setFactorSolverType("mumps")
        self.ksp.setErrorIfNotConverged(True)
        self._rhs, self._sol = self.M.createVecs()
        self._q = basis.matrix.createVecLeft()

    def update(self) -> bool:
        """Follow :meth:`FieldBasis.update` of the basis: values only (numeric refactorisation)
        when its sparsity is unchanged, else submatrix, M and factorisation anew. Collective.
        Returns True if the sparsity was rebuilt."""
        rebuilt = self._pattern != self.basis.pattern_version
        self._assemble()
        return rebuilt

    def project(self, q: np.ndarray, u: dolfinx.fem.Function) -> np.ndarray:
        """Prescribed-dof values D^ (len(prescribed),) from particle values q (n, value_size).

        ``u`` supplies the free dofs D (its prescribed entries are ignored). Collective.
        """
        basis = self.basis
        u.x.scatter_forward()
        D0 = u.x.array.copy()
        D0[self._mask] = 0.0
        r = np.asarray(q, dtype=np.float64).reshape(-1) - basis.local @ D0  # Q - N_D D
        if r.size != self._q.getLocalSize():
            raise ValueError(f"q has {r.size} values, expected {self._q.getLocalSize()}")
        self._q.setArray(r)
        self.N_hat.multTranspose(self._q, self._rhs)
        try:
            self.ksp.solve(self._rhs, self._sol)
        except PETSc.Error as err:
            raise SingularProjection(
                "factorising M = N^T N failed (rank deficient: too few particles per element "
                "for the field's degree); pass regularization > 0"
            ) from err
        return self._sol.getArray().copy()

    def apply(self, q: np.ndarray, u: dolfinx.fem.Function) -> None:
        """Write the projected values into the prescribed dofs of ``u`` and update ghosts."""
        u.x.array[self.prescribed] = self.project(q, u)
        u.x.scatter_forward()
