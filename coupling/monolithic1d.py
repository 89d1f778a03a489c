"""Monolithic Newton coupling of a glued sphere string and a micropolar rod (seed 001 §2.4.3-2.4.4).

Both set-ups are written as one map from the unknowns X to all FE dofs, ``D = T X``, and
one residual (serial, small dense systems)::

    R(X) = S^T Fw_DE(S X) + T^T Fw_FE(T X) - F_ext = 0

with ``S`` selecting the particle dofs Q from X, ``Fw_DE`` the glued-string internal force
(:mod:`dem.glued`) with per-contact row weights and ``Fw_FE = W K D`` the rod internal force
(:mod:`granfe.rod1d`) with per-cell row weights W.

* Full overlap (eq. 122): X = Q (all particles free), ``D_free = B Q`` with
  ``B = M^-1 N^T``, ``M = N^T N`` (N: rod basis at the sphere centres, eq. 74-78, clamped
  FE dofs removed). DE rows weighted by ``1 - q^k``, FE rows by ``q^k`` per field k; since
  N is block-diagonal by field this equals ``(1 - q) F^DE(Q) + q B^T K B Q`` of eq. 122.
* Partial overlap (eq. 123-126): X = (Q, D_free); the FE dofs at nodes inside the particle
  string are prescribed, ``D^ = M^-1 N^^T (Q_o - N_QD D)`` over the overlap particles
  (eq. 79-90); R^Q and R^D of eq. 125-126 follow from the chain rule through T.
  Weights: FE cells fully under particles (B^h^) ``q^k``, the transition cell (B^h~)
  ``q^ + (1 - q^) q^k`` (volume fraction q^, eq. 119), pure FE 1; DE contacts inside
  the FE span ``1 - q^k``, others 1. These combination rules are our reading of §2.4.4.
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401

from dataclasses import dataclass

import numpy as np

from coupling.operators import FieldBasis
from dem.glued import GluedString, NewtonReport, newton
from granfe.rod1d import Rod1D

__all__ = ["Coupled1D", "full_overlap", "partial_overlap", "rod_basis"]

FIELDS = ("u", "v", "theta")


def rod_basis(rod: Rod1D, x: np.ndarray) -> np.ndarray:
    """N (3 n, n_dofs): particle dof ``3 a + k`` = field k of the rod at x[a] (eq. 74-78)."""
    rows = [FieldBasis.build(rod.V, x[:, None], sub=k).local.toarray() for k in range(3)]
    N = np.zeros((3 * x.size, rows[0].shape[1]))
    for k in range(3):
        N[k::3] = rows[k]
    return N


@dataclass
class Coupled1D:
    """The assembled coupled problem; build with :func:`full_overlap` or :func:`partial_overlap`.

    Attributes:
        string, rod: the two models.
        T: (n_fe_dofs, n_X) map X -> all FE dofs; S: (3 n, n_X) map X -> Q.
        w_de: (n - 1, 3) per-contact row weights of (f_x, f_y, f_th).
        fixed: X indices held at zero (clamps).
    """

    string: GluedString
    rod: Rod1D
    T: np.ndarray
    S: np.ndarray
    w_de: np.ndarray
    fixed: np.ndarray

    @property
    def n(self) -> int:
        return self.T.shape[1]

    def de_force(self, Q: np.ndarray) -> np.ndarray:
        """Weighted DE internal force (3 n,) (eq. 62 with row weights)."""
        return self.string.f_int(Q, self.w_de)

    def de_tangent(self, Q: np.ndarray) -> np.ndarray:
        """Weighted DE consistent tangent (3 n, 3 n) (eq. 63-65)."""
        return self.string.tangent(Q, self.w_de)

    def residual(self, X: np.ndarray, f_ext: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(R (n_X,), dR/dX (n_X, n_X)) of eq. 122 / 125-126."""
        Q = self.S @ X
        K_fe = self.rod.K.toarray()
        r = self.S.T @ self.de_force(Q) + self.T.T @ (K_fe @ (self.T @ X)) - f_ext
        J = self.S.T @ self.de_tangent(Q) @ self.S + self.T.T @ K_fe @ self.T
        return r, J

    def solve(self, f_ext: np.ndarray, X0: np.ndarray, **kw) -> tuple[np.ndarray, NewtonReport]:
        """Newton with line search (:func:`dem.glued.newton`) from X0; returns (X, report)."""
        return newton(lambda X: self.residual(X, f_ext), X0, self.fixed,
                      scale=max(np.abs(f_ext).max(), 1.0), **kw)

    def force_split(self, X: np.ndarray, dof: int) -> tuple[float, float]:
        """(DE part, projected FE part) [N] of the internal force at X-dof ``dof``."""
        Q = self.S @ X
        de = (self.S.T @ self.de_force(Q))[dof]
        fe = (self.T.T @ (self.rod.K @ (self.T @ X)))[dof]
        return float(de), float(fe)

    def fields(self, X: np.ndarray) -> dict:
        """Particle (x, u, v, theta) and node (x, values) per field, as lists [m, rad]."""
        Q = (self.S @ X).reshape(-1, 3)
        D = self.T @ X
        out = {"particles": {"x": self.string.x.tolist(), "u": Q[:, 0].tolist(),
                             "v": Q[:, 1].tolist(), "theta": Q[:, 2].tolist()}, "nodes": {}}
        for name in FIELDS:
            dofs, x = self.rod.field_dofs[name]
            out["nodes"][name] = {"x": x.tolist(), "value": D[dofs].tolist()}
        return out


def _field_weights(rod: Rod1D, q) -> None:
    for k, name in enumerate(FIELDS):
        rod.set_cell_weights(name, q[k])


def full_overlap(string: GluedString, rod: Rod1D, q=(0.0, 0.0, 0.0)) -> Coupled1D:
    """Eq. 122: rod and string over the same span, rod clamped at its right end, X = Q.

    ``q = (q_u, q_v, q_theta)`` in [0, 1): FE share of each balance equation; q = 1 leaves
    the particle dofs outside the range of B singular, so it is refused.
    """
    q = np.asarray(q, dtype=float)
    if q.shape != (3,) or np.any(q < 0) or np.any(q >= 1):
        raise ValueError(f"q must be three numbers in [0, 1), got {q!r}")
    N = rod_basis(rod, string.x)
    n_fe = N.shape[1]
    clamp = rod.end_dofs("right")
    free_d = np.setdiff1d(np.arange(n_fe), clamp)
    Nf = N[:, free_d]
    B = np.linalg.solve(Nf.T @ Nf, Nf.T)  # eq. 122: B_DQ = M^-1 N^T
    T = np.zeros((n_fe, string.n_dofs))
    T[free_d] = B
    _field_weights(rod, q)
    w_de = np.tile(1.0 - q, (string.n - 1, 1))
    return Coupled1D(string, rod, T, np.eye(string.n_dofs), w_de, string.clamp_dofs("right"))


def partial_overlap(string: GluedString, rod: Rod1D, q_hat: float,
                    q=(0.0, 0.0, 0.0)) -> Coupled1D:
    """Eq. 123-126: the rod starts inside the string and extends beyond it (clamped at its right).

    FE dofs at x <= last sphere centre are prescribed by the L2 projection of the particles
    with centres in the rod span; ``q_hat`` weights the FE in the cell holding the string's
    end (B^h~), ``q`` factors the energy in the overlap (see module doc).
    """
    q = np.asarray(q, dtype=float)
    if not 0.0 <= q_hat <= 1.0:
        raise ValueError(f"q_hat must lie in [0, 1], got {q_hat!r}")
    if q.shape != (3,) or np.any(q < 0) or np.any(q > 1):
        raise ValueError(f"q must be three numbers in [0, 1], got {q!r}")
    x_end, x_rod = string.x[-1], rod.x0
    h = rod.length / rod.mesh.topology.index_map(1).size_local
    in_rod = string.x >= x_rod - 1e-12
    N = rod_basis(rod, string.x[in_rod])
    n_fe, nq = N.shape[1], string.n_dofs
    xs = np.empty(n_fe)
    for name in FIELDS:
        dofs, x = rod.field_dofs[name]
        xs[dofs] = x
    pres = np.flatnonzero(xs <= x_end + 1e-12)
    clamp = rod.end_dofs("right")
    free_d = np.setdiff1d(np.arange(n_fe), np.concatenate([pres, clamp]))
    Np, Nd = N[:, pres], N[:, free_d]
    P = np.linalg.solve(Np.T @ Np, Np.T)  # eq. 79-90
    qrows = np.flatnonzero(np.repeat(in_rod, 3))
    T = np.zeros((n_fe, nq + free_d.size))
    T[free_d, nq + np.arange(free_d.size)] = 1.0
    T[np.ix_(pres, qrows)] = P
    T[np.ix_(pres, nq + np.arange(free_d.size))] = -P @ Nd
    S = np.zeros((nq, T.shape[1]))
    S[:, :nq] = np.eye(nq)
    for k, name in enumerate(FIELDS):
        def weight(xm, k=k):
            under = xm + h / 2 <= x_end + 1e-12
            trans = (~under) & (xm - h / 2 < x_end)
            return np.where(under, q[k], np.where(trans, q_hat + (1 - q_hat) * q[k], 1.0))
        rod.set_cell_weights(name, weight)
    xc = 0.5 * (string.x[:-1] + string.x[1:])
    w_de = np.where((xc >= x_rod)[:, None], 1.0 - q[None, :], 1.0)
    # the clamp is removed from X (not in free_d) and every particle is free: nothing held
    return Coupled1D(string, rod, T, S, w_de, np.array([], dtype=int))
