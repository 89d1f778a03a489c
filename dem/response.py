"""A force linear in the particles' displacement since a reference state, through a sparse
linear solve: a pore fluid's response between two of its steps, linearised.

A fluid solved every few DEM steps answers the grains' displacement u since its last step
(positions x_ref) with a pressure change, and the pressure change with forces on them. The
coupling layer hands that answer over as plain sparse matrices, and the DEM applies it at
every step in its own loop (the fused one too):

    f = T A^-1 (S u - k r),       u = (x - x_ref) of rows, components 0..d-1, ravelled,

with A^-1 by its sparse LU factors (``Pr A Pc = L U``, scipy's SuperLU convention), S the
displacement's source, r a drift per step (the last pressure's drainage), k the number of
steps since the reference, T the pressure's force on the rows. `dem.Simulation.step` adds
f to the FREE rows' forces where it applies a drag (after the force pass, before the
second half-kick), and sets their kick flags.

Nothing here knows what the matrices are: `coupling` builds them.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numba import njit

from dem.state import FREE

__all__ = ["LinearResponse", "applies"]


@njit(cache=True)
def _csr_matvec(ptr, ind, val, x, out):
    for i in range(ptr.shape[0] - 1):
        acc = 0.0
        for q in range(ptr[i], ptr[i + 1]):
            acc += val[q] * x[ind[q]]
        out[i] = acc


@njit(cache=True)
def _to_nodes(x, rows, xref, nodes, to_nodes, u, w):
    """The displacement u = (x - xref) of rows, ravelled, and w its nodal sums by the basis
    table."""
    m, d = xref.shape
    w[:] = 0.0
    for k in range(m):
        for c in range(d):
            u[k * d + c] = x[rows[k], c] - xref[k, c]
        for a in range(nodes.shape[1]):
            j = nodes[k, a]
            if j >= 0:
                for c in range(d):
                    w[j * d + c] += to_nodes[k, a] * u[k * d + c]


@njit(cache=True)
def _lu_solve(b, l_ptr, l_ind, l_val, u_ptr, u_ind, u_val, inv_diag, perm_r, perm_c, y, z):
    """The solution y = A^-1 b from SuperLU's factors ``Pr A Pc = L U`` (L's strict lower
    part, U's strict upper part and the inverse of its diagonal; z scratch)."""
    nb = b.shape[0]
    for i in range(nb):
        y[perm_r[i]] = b[i]
    for i in range(nb):                     # L y' = y (forward, unit diagonal)
        acc = y[i]
        for q in range(l_ptr[i], l_ptr[i + 1]):
            acc -= l_val[q] * y[l_ind[q]]
        y[i] = acc
    for i in range(nb - 1, -1, -1):         # U z = y' (backward)
        acc = y[i]
        for q in range(u_ptr[i], u_ptr[i + 1]):
            acc -= u_val[q] * z[u_ind[q]]
        z[i] = acc * inv_diag[i]
    for i in range(nb):
        y[i] = z[perm_c[i]]


@njit(cache=True)
def _from_nodes(g, weight, force, kind, hit, rows, nodes, from_nodes, d, out):
    """The nodal forces g times weight taken by the FREE rows through the basis table into
    out, added to their forces, their flags set."""
    for k in range(rows.shape[0]):
        i = rows[k]
        out[k, :] = 0.0
        if kind[i] != FREE:
            continue
        for c in range(d):
            acc = 0.0
            for a in range(nodes.shape[1]):
                j = nodes[k, a]
                if j >= 0:
                    acc += from_nodes[k, a] * g[j * d + c]
            acc *= weight
            out[k, c] = acc
            force[i, c] += acc
        hit[i] = 1


@njit(cache=True)
def applies(k, s) -> bool:
    """Whether the k-th step (from 1) since the reference applies a response of stride s: one
    step's force stands for the block of s steps it is the middle of (steps b s + 1 ..
    (b + 1) s, applied at b s + (s - 1) // 2 + 1: never at a block's last step, which ends a
    fluid interval whose next step replaces the forces before the second half of the kick).
    A hook that applies such a response itself (the 2-rank fluid) takes its steps from here."""
    return s <= 1 or (k - 1) % s == (s - 1) // 2


@njit(cache=True)
def linear_response(x, force, kind, hit, rows, xref, nodes, to_nodes, from_nodes, s_ptr, s_ind,
                    s_val, r, l_ptr, l_ind, l_val, u_ptr, u_ind, u_val, inv_diag, perm_r, perm_c,
                    t_ptr, t_ind, t_val, count, u, w, b, y, z, g, out):
    """Add ``f = T A^-1 (S u - k r)`` (the module docstring) to the forces of the FREE rows
    among ``rows`` (m,), and set their flags in ``hit``; count (3,): [0] (k) counts the
    calls since the reference, [1] the stride s (at s > 1 only every s-th call applies a
    force, s times the call's: :func:`applies`), [2] whether out holds a force. xref (m, d)
    [m]; the basis tables nodes, to_nodes, from_nodes (m, q) (a node -1: none); S (nb, nn d),
    T (nn d, nb) CSR; L, U the CSR factors of A without their diagonals (L's is 1) and the
    inverse of U's, perm_r / perm_c SuperLU's permutations; u (m d,), w, g (nn d,), b, y, z
    (nb,) scratch; out (m, 3) the force [N] added at this call (0 at a skipped one)."""
    count[0] += 1
    if not applies(count[0], count[1]):
        if count[2]:
            out[:] = 0.0
            count[2] = 0
        return
    _to_nodes(x, rows, xref, nodes, to_nodes, u, w)
    _csr_matvec(s_ptr, s_ind, s_val, w, b)
    k = float(count[0])
    for i in range(b.shape[0]):
        b[i] -= k * r[i]
    _lu_solve(b, l_ptr, l_ind, l_val, u_ptr, u_ind, u_val, inv_diag, perm_r, perm_c, y, z)
    _csr_matvec(t_ptr, t_ind, t_val, y, g)
    _from_nodes(g, float(max(count[1], 1)), force, kind, hit, rows, nodes, from_nodes, xref.shape[1], out)
    count[2] = 1


def _csr(M):
    M = sp.csr_matrix(M)
    return (np.ascontiguousarray(M.indptr, np.int64), np.ascontiguousarray(M.indices, np.int32),
            np.ascontiguousarray(M.data, float))


def _factors(lu) -> tuple:
    """The kernel's factor arrays of ``lu``: its own (`dem.ldl.LDL.kernel_arrays`) or
    SuperLU's, the diagonals apart (the solves' inner loops without a branch)."""
    if hasattr(lu, "kernel_arrays"):
        return lu.kernel_arrays()
    diag = lu.U.diagonal()
    if not (np.isfinite(diag).all() and (diag != 0).all()):
        raise ValueError("LinearResponse: A is singular (a zero pivot in its LU factors)")
    return (*_csr(sp.tril(lu.L, k=-1)), *_csr(sp.triu(lu.U, k=1)), 1.0 / diag,
            np.ascontiguousarray(lu.perm_r, np.int64), np.ascontiguousarray(lu.perm_c, np.int64))


class LinearResponse:
    """The force ``f = T A^-1 (S u - k r)`` of the module docstring, from one reference
    state on.

    Args:
        rows: (m,) the particles whose displacement drives it and which take it.
        x_ref: (m, d) [m] their positions at the reference (d = 2 or 3 components used).
        source: S, sparse (nb, nn d) on nodal vectors (node j's component c at j d + c).
        drift: r, (nb,), subtracted k times at the k-th step since the reference.
        lu: the factors of A (nb, nb): SuperLU's (`scipy.sparse.linalg.splu`) or a
            `dem.ldl.LDL` (symmetric positive definite A of a fixed pattern: refactored
            without its analysis).
        force: T, sparse (nn d, nb) [N per unit of A^-1's result] to nodal vectors.
        basis: (nodes, to_nodes, from_nodes), each (m, q): particle k's displacement goes
            to node nodes[k, a] times to_nodes[k, a], and it takes the nodal force times
            from_nodes[k, a] (a node -1: none). None: the nodes are the particles (nn = m,
            weights 1). A basis evaluated at the particles keeps S and T the mesh's own
            (fixed) operators, the per-step work ~q m d more than theirs.
        stride: s >= 1 steps per application. At s > 1 the force is multiple time stepping's
            impulse (Tuckerman, Berne & Martyna 1992: r-RESPA's slow force): s times the
            force of the middle step of each block of s steps since the reference, nothing
            at the others, so the kicks give each block the impulse s dt f. It is stable
            and second order while ``s dt omega`` stays well below 2 (omega the response's
            stiffest frequency over the particles' masses; ~0.3 keeps the phase error
            ~0.4 %), and costs a step 1/s of the response (:func:`applies`: which steps).

    Use: ``sim.step(n, response=resp)``; a new reference: :meth:`reset` (positions only)
    or :meth:`update`. :attr:`force` holds the force of the last step (m, 3) [N].
    """

    def __init__(self, rows, x_ref, source, drift, lu, force, basis=None, stride=1):
        #: [steps since the reference, the stride, whether :attr:`force` is not 0]
        self.count = np.zeros(3, np.int64)
        self.stride = stride
        self.update(rows, x_ref, source, drift, lu, force, basis)

    @property
    def stride(self) -> int:
        """Steps per application (the class docstring); set between blocks."""
        return int(self.count[1])

    @stride.setter
    def stride(self, s: int) -> None:
        if isinstance(s, bool) or not isinstance(s, int | np.integer) or s < 1:
            raise ValueError(f"LinearResponse: stride must be an integer >= 1, got {s!r}")
        self.count[1] = s

    def update(self, rows, x_ref, source, drift, lu, force, basis=None) -> None:
        """A new reference and new operators (the arguments as the constructor's), in this
        object: a `dem.Simulation.step` call that holds it takes them up at its next step
        (a pause may call this); the step count back to 0."""
        self.rows = np.ascontiguousarray(rows, np.int64)
        m = len(self.rows)
        self.x_ref = np.array(x_ref, float, order="C")   # (a copy: never a view of x)
        if self.x_ref.ndim != 2 or self.x_ref.shape[0] != m or self.x_ref.shape[1] not in (2, 3):
            raise ValueError(f"LinearResponse: x_ref must be ({m}, 2 or 3), got {self.x_ref.shape}")
        d = self.x_ref.shape[1]
        nb = lu.shape[0]
        if basis is None:
            basis = (np.arange(m)[:, None], np.ones((m, 1)), np.ones((m, 1)))
        nodes = np.ascontiguousarray(basis[0], np.int64)
        to_nodes, from_nodes = (np.ascontiguousarray(a, float) for a in basis[1:])
        if nodes.ndim != 2 or nodes.shape[0] != m or to_nodes.shape != nodes.shape \
                or from_nodes.shape != nodes.shape:
            raise ValueError(f"LinearResponse: basis tables must be ({m}, q) alike, got "
                             f"{[np.shape(a) for a in basis]}")
        nn = source.shape[1] // d
        if source.shape != (nb, nn * d) or force.shape != (nn * d, nb) or nodes.max(initial=-1) >= nn:
            raise ValueError(f"LinearResponse: source must be ({nb}, nn {d}) and force "
                             f"(nn {d}, {nb}) with every node < nn, got {source.shape} and "
                             f"{force.shape}, nodes up to {nodes.max(initial=-1)}")
        self.drift = np.ascontiguousarray(drift, float).reshape(-1)
        if self.drift.shape != (nb,) or not np.isfinite(self.drift).all():
            raise ValueError(f"LinearResponse: drift must be ({nb},) and finite")
        self._ops = (nodes, to_nodes, from_nodes, *_csr(source), self.drift, *_factors(lu),
                     *_csr(force))
        self.count[0] = self.count[2] = 0
        self.force = np.zeros((m, 3))   #: the force of the last step [N]
        self._scratch = (np.zeros(m * d), np.zeros(nn * d), np.zeros(nb), np.zeros(nb),
                         np.zeros(nb), np.zeros(nn * d))

    def reset(self, x_ref) -> None:
        """A new reference (positions (m, d) [m]), the step count back to 0."""
        self.x_ref[:] = x_ref
        self.count[0] = 0

    def arrays(self) -> tuple:
        """The kernel's arguments after (x, force, kind, hit) (`dem.fused_steps`' loop too)."""
        return (self.rows, self.x_ref, *self._ops, self.count, *self._scratch, self.force)

    def apply(self, sim) -> None:
        """Add the force of the next step since the reference to the forces of ``sim``."""
        p = sim.p
        linear_response(p.x, p.force, p.kind, sim.forced, *self.arrays())

    def withdraw(self, sim) -> None:
        """Take the last step's force out of the forces of ``sim`` (before a new reference's
        own forces are set: between steps)."""
        free = sim.p.kind[self.rows] == FREE
        sim.p.force[self.rows[free]] -= self.force[free]
        self.force[:] = 0.0
        self.count[2] = 0
