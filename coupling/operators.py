"""Interpolation and projection operators between FE dofs and particle centroids.

``N`` evaluates the FE basis of one field (a sub-space of a mixed space: u or phi) at the
particle centroids, seed 001 eq. 74-78: ``Q = N D``. It is a distributed PETSc matrix with
one row per particle component (rows owned by the rank owning the particle's cell) and one
column per dof of the *parent* space (its global numbering), so it acts directly on
``Function.x.petsc_vec`` of the mixed solution.

``NodalProjection`` is the discrete L2 projection of particle motion onto the prescribed
nodes of the overlap, seed 001 eq. 79-90: ``D^ = M^-1 N^^T (Q - N_D D)`` with
``M = N^^T N^`` where ``N^`` holds the columns of the prescribed dofs.
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401  (orders MPI before the dolfinx bindings)

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc

import dolfinx.fem
import dolfinx.la

from coupling.locate import locate_owned, pad_points

__all__ = ["FieldBasis", "NodalProjection", "SingularProjection"]


class SingularProjection(ValueError):
    """The projection matrix M is singular: named dofs have too few particles in their support."""


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
    """

    V: dolfinx.fem.FunctionSpace
    sub: int | None
    value_size: int
    matrix: PETSc.Mat
    local: sp.csr_matrix
    dofs: np.ndarray
    dof_coordinates: np.ndarray
    particle_offset: int

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
        Vs = V if sub is None else V.sub(sub)
        Vc, parent = Vs.collapse()
        parent = np.asarray(parent[0] if isinstance(parent, list) else parent, dtype=np.int64)
        if Vc.element.needs_dof_transformations:
            raise NotImplementedError(
                "FieldBasis supports elements without dof transformations (Lagrange up to P2)"
            )
        ufl_el = Vc.ufl_element()
        scalar = ufl_el.sub_elements[0] if ufl_el.block_size > 1 else ufl_el
        bs = Vc.dofmap.bs
        phi = scalar.basix_element.tabulate(0, X)[0, :, :, 0] if len(X) else np.zeros((0, 0))

        n_local = x.shape[0]
        offset = comm.exscan(n_local) or 0
        n_global = comm.allreduce(n_local)
        imap, bsV = V.dofmap.index_map, V.dofmap.bs
        n_parent_local = (imap.size_local + imap.num_ghosts) * bsV

        rows, cols, vals = [], [], []
        for i, c in enumerate(cells):
            cdofs = Vc.dofmap.cell_dofs(c)
            for k in range(bs):
                rows.append(np.full(cdofs.size, i * bs + k))
                cols.append(parent[cdofs * bs + k])
                vals.append(phi[i])
        if rows:
            rows, cols, vals = (np.concatenate(a) for a in (rows, cols, vals))
        else:
            rows, cols, vals = (np.zeros(0, dtype=t) for t in (np.int64, np.int64, float))
        local = sp.csr_matrix((vals, (rows, cols)), shape=(n_local * bs, n_parent_local))
        local.sum_duplicates()

        blocks = np.arange(n_parent_local) // bsV
        global_cols = imap.local_to_global(blocks.astype(np.int32)) * bsV + np.arange(
            n_parent_local
        ) % bsV
        n_dofs_owned, n_dofs_global = imap.size_local * bsV, imap.size_global * bsV
        A = PETSc.Mat().createAIJ(
            ((n_local * bs, n_global * bs), (n_dofs_owned, n_dofs_global)),
            nnz=(scalar.basix_element.dim, scalar.basix_element.dim),
            comm=comm,
        )
        A.setUp()
        for r in range(local.shape[0]):
            lo, hi = local.indptr[r], local.indptr[r + 1]
            A.setValues(
                offset * bs + r,
                global_cols[local.indices[lo:hi]].astype(PETSc.IntType),
                local.data[lo:hi],
            )
        A.assemble()

        dofs = np.unique(parent)
        coords_c = Vc.tabulate_dof_coordinates()
        dof_coordinates = np.empty((dofs.size, 3))
        dof_coordinates[np.searchsorted(dofs, parent)] = np.repeat(coords_c, bs, axis=0)[
            : parent.size
        ]
        return cls(V, sub, bs, A, local.tocsr(), dofs, dof_coordinates, offset)

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
    M is factorised once (MUMPS) and reused until particles change cells.

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
        rlo, rhi = basis.matrix.getOwnershipRange()
        rows = PETSc.IS().createStride(rhi - rlo, first=rlo, step=1, comm=comm)
        self.N_hat = basis.matrix.createSubMatrix(rows, self._cols)
        self.M = self.N_hat.transposeMatMult(self.N_hat)
        diag = self.M.getDiagonal()
        d = diag.getArray().copy()
        scale = comm.allreduce(d.sum()) / max(comm.allreduce(d.size), 1)
        empty = np.flatnonzero(d <= 1e-14 * max(scale, 1e-300))
        if regularization > 0.0:
            diag.set(regularization * scale)
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
        self.ksp = PETSc.KSP().create(comm)
        self.ksp.setOperators(self.M)
        self.ksp.setType("preonly")
        pc = self.ksp.getPC()
        pc.setType("cholesky")
        pc.setFactorSolverType("mumps")
        self.ksp.setErrorIfNotConverged(True)
        self._rhs, self._sol = self.M.createVecs()
        self._q = basis.matrix.createVecLeft()

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
