"""Sparse LDL^T factors of a symmetric matrix whose pattern stays while its values change,
in the form `dem.response.LinearResponse` reads (SuperLU's: ``Pr A Pc = L U``).

A pore fluid's system matrix M + dt K changes its values at every fluid step (porosity,
permeability) but never its pattern (the mesh's). scipy's SuperLU orders and analyses the
pattern anew at each factorisation (2 ms on 672 dofs, 5x the numeric work); here the
fill-reducing order and the elimination tree are found once (`LDL.__init__`) and every
refactorisation is the numeric pass alone (`LDL.factor`): the up-looking LDL^T of T. A.
Davis's LDL package (ACM TOMS 31, 2005, Algorithm 849), no pivoting, so for symmetric
positive definite matrices (a singular or indefinite one is refused by its zero or
negative pivot).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy.sparse.linalg import splu

from dem.response import _lu_solve

__all__ = ["LDL"]


@njit(cache=True)
def _symbolic(n, ap, ai, perm, pinv, lp, parent, lnz, flag):
    """The elimination tree (parent) and column counts (lnz -> pointers lp) of the
    permuted matrix C = A[perm][:, perm] (A CSC, its upper part used)."""
    for k in range(n):
        parent[k] = -1
        flag[k] = k
        lnz[k] = 0
        kk = perm[k]
        for p in range(ap[kk], ap[kk + 1]):
            i = pinv[ai[p]]
            if i < k:
                while flag[i] != k:
                    if parent[i] == -1:
                        parent[i] = k
                    lnz[i] += 1
                    flag[i] = k
                    i = parent[i]
    lp[0] = 0
    for k in range(n):
        lp[k + 1] = lp[k] + lnz[k]


@njit(cache=True)
def _numeric(n, ap, ai, ax, perm, pinv, lp, parent, lnz, li, lx, d, y, pattern, flag):
    """L (CSC, strictly lower: li, lx in lp) and D of C = A[perm][:, perm] = L D L^T.
    Returns n, or the column k whose pivot is not positive."""
    for k in range(n):
        y[k] = 0.0
        top = n
        flag[k] = k
        lnz[k] = 0
        kk = perm[k]
        for p in range(ap[kk], ap[kk + 1]):
            i = pinv[ai[p]]
            if i <= k:
                y[i] += ax[p]
                length = 0
                while flag[i] != k:
                    pattern[length] = i
                    length += 1
                    flag[i] = k
                    i = parent[i]
                while length > 0:
                    top -= 1
                    length -= 1
                    pattern[top] = pattern[length]
        d[k] = y[k]
        y[k] = 0.0
        while top < n:
            i = pattern[top]
            yi = y[i]
            y[i] = 0.0
            p2 = lp[i] + lnz[i]
            for p in range(lp[i], p2):
                y[li[p]] -= lx[p] * yi
            lki = yi / d[i]
            d[k] -= lki * yi
            li[p2] = k
            lx[p2] = lki
            lnz[i] += 1
            top += 1
        if not d[k] > 0.0:
            return k
    return n


@njit(cache=True)
def _transpose(n, lp, li, lx, rp, ri, rx, fill):
    """The CSR (rp, ri, rx) of the CSC (lp, li, lx): L's rows (fill: n scratch)."""
    rp[:] = 0
    for p in range(lp[n]):
        rp[li[p] + 1] += 1
    for i in range(n):
        rp[i + 1] += rp[i]
        fill[i] = rp[i]
    for j in range(n):
        for p in range(lp[j], lp[j + 1]):
            q = fill[li[p]]
            ri[q] = j
            rx[q] = lx[p]
            fill[li[p]] += 1


def _columns(A):
    """(indptr, indices, data) of A's columns: a CSR matrix's own arrays are its transpose's
    columns, A's for a symmetric A (no conversion); any other format converted."""
    if not (sp.issparse(A) and A.format == "csr"):
        A = sp.csc_matrix(A)
    return A.indptr, A.indices, A.data


class LDL:
    """LDL^T factors of symmetric positive definite matrices of one pattern.

    Args:
        A: the pattern (and first values) as a scipy sparse matrix (n, n), symmetric in
            pattern and values.

    :meth:`factor` takes new values of the same pattern; :meth:`kernel_arrays` gives the
    factors as `dem.response.LinearResponse` reads them (``Pr A Pc = L U`` with L unit
    lower and U = D L^T).
    """

    def __init__(self, A):
        n = A.shape[0]
        if A.shape != (n, n):
            raise ValueError(f"LDL: A must be square, got {A.shape}")
        self.shape = A.shape
        ap, ai, _ = _columns(A)
        self._ap, self._ai = ap.astype(np.int64), ai.astype(np.int64)
        # a fill-reducing order of A + A^T (SuperLU's minimum degree, found once)
        order = splu(sp.csc_matrix(A), permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True}).perm_c
        self.perm = np.argsort(order).astype(np.int64)   # C = A[perm][:, perm]
        self.pinv = np.argsort(self.perm).astype(np.int64)
        self.perm_r = self.perm_c = self.pinv
        self._lp, self._parent = np.zeros(n + 1, np.int64), np.zeros(n, np.int64)
        self._lnz, self._flag = np.zeros(n, np.int64), np.zeros(n, np.int64)
        _symbolic(n, self._ap, self._ai, self.perm, self.pinv, self._lp, self._parent,
                  self._lnz, self._flag)
        nnz = int(self._lp[-1])
        self._li, self._lx = np.zeros(nnz, np.int64), np.zeros(nnz)
        self._rp, self._ri, self._rx = np.zeros(n + 1, np.int64), np.zeros(nnz, np.int32), np.zeros(nnz)
        self._fill = np.zeros(n, np.int64)
        self.d, self._y, self._pattern = np.zeros(n), np.zeros(n), np.zeros(n, np.int64)
        self.factor(A)

    def same_pattern(self, A) -> bool:
        """Whether A has the pattern (and the storage order) the factors were analysed for."""
        ap, ai, _ = _columns(A)
        return np.array_equal(ap, self._ap) and np.array_equal(ai, self._ai)

    def factor(self, A) -> LDL:
        """Factor new values of the pattern (A symmetric, in the storage it was analysed
        in); returns self."""
        ap, ai, ax = _columns(A)
        if not (np.array_equal(ap, self._ap) and np.array_equal(ai, self._ai)):
            raise ValueError("LDL.factor: A's pattern is not the one analysed (build a new LDL)")
        n = self.shape[0]
        k = _numeric(n, self._ap, self._ai, np.asarray(ax, float), self.perm, self.pinv,
                     self._lp, self._parent, self._lnz, self._li, self._lx, self.d, self._y,
                     self._pattern, self._flag)
        if k < n:
            raise ValueError(f"LDL.factor: pivot {k} is {self.d[k]!r}: A is not symmetric "
                             f"positive definite")
        _transpose(n, self._lp, self._li, self._lx, self._rp, self._ri, self._rx, self._fill)
        self._kernel = None
        return self

    def kernel_arrays(self) -> tuple:
        """(L's strict lower part as CSR (ptr, ind, val), U's strict upper part as CSR, the
        inverse of U's diagonal, perm_r, perm_c): ``Pr A Pc = L U``, U = D L^T, whose row
        i is L's column i times d_i (made once a factorisation)."""
        if self._kernel is None:
            u_val = self._lx * np.repeat(self.d, np.diff(self._lp))
            self._kernel = (self._rp, self._ri, self._rx, self._lp, self._li.astype(np.int32), u_val,
                            1.0 / self.d, self.perm_r, self.perm_c)
        return self._kernel

    def solve(self, b: np.ndarray) -> np.ndarray:
        """A^-1 b (n,): the response kernel's substitutions (numba)."""
        b = np.ascontiguousarray(b, dtype=float)
        if b.shape != (self.shape[0],):
            raise ValueError(f"LDL.solve: b must be ({self.shape[0]},), got {b.shape}")
        y = np.empty_like(b)
        _lu_solve(b, *self.kernel_arrays(), y, np.empty_like(b))
        return y
