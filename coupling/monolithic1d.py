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
* Axial waves (eq. 108-121, linear): :func:`axial_overlap` couples the rod's axial field
  (left) with a linear :class:`dem.glued.SpringString` (right) through an overlap of prescribed
  FE nodes; kinetic (r) and potential (q) energy shares are segment means of one partition
  of unity, and :class:`AverageAcceleration` integrates ``M X'' + K X = 0`` conserving the
  discrete energy.
"""

from __future__ import annotations

from dataclasses import dataclass

import dolfinx_solver  # noqa: F401

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from coupling.operators import FieldBasis
from dem.glued import GluedString, NewtonReport, SpringString, newton
from granfe.rod1d import Rod1D

__all__ = ["AverageAcceleration", "AxialOverlap1D", "Coupled1D", "axial_overlap", "full_overlap",
           "partial_overlap", "rod_axial", "rod_basis"]

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


# ---- axial waves through the overlap (eq. 108-121, linear, one field) ---------------------------

WEIGHTINGS = ("ramp", "volume", "volume_equal")
REGIONS = ("fe", "overlap", "de")


def particle_share(lo, hi, s0: float, s1: float) -> np.ndarray:
    """Mean over [lo, hi] of the particles' energy share g(s): 0 for s < s0, linear up to 1 at
    s1, 1 beyond (a step at s0 when s1 == s0). The FE share is 1 - g, so every segment's
    mass and stiffness are split exactly (seed 001 eq. 110-121, r = q)."""
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    width = s1 - s0

    def primitive(s):
        if width > 0:
            return np.where(s < s0, 0.0, np.where(s <= s1, (s - s0) ** 2 / (2 * width),
                                                  width / 2 + s - s1))
        return np.maximum(s - s0, 0.0)

    return (primitive(hi) - primitive(lo)) / (hi - lo)


@dataclass
class AxialOverlap1D:
    """Linear axial dynamics ``M X'' + K X = 0`` of a rod overlapped with a spring string.

    X = (Q (n particles), D_free); FE axial dofs ``D = T X`` with the overlap nodes prescribed
    by the L2 projection of the particles under the rod (eq. 79-90). ``M``, ``K`` (n_X, n_X)
    are symmetric; ``parts[region] = (M_r, K_r)`` split them by where each cell, spring and
    particle sits: "fe" (x < x_a), "overlap" [x_a, x_b], "de" (x > x_b).

    Attributes: rod, string, T (n_u, n_X), M, K, parts, x_a (first particle), x_b (rod end),
    u_x (n_u,) abscissae of the rod's axial dofs, free (FE dof positions in X).
    """

    rod: Rod1D
    string: SpringString
    T: sp.csr_matrix
    M: sp.csr_matrix
    K: sp.csr_matrix
    parts: dict
    x_a: float
    x_b: float
    u_x: np.ndarray
    free: np.ndarray

    def energy(self, X: np.ndarray, V: np.ndarray, region: str | None = None) -> float:
        """Kinetic + potential energy [J] of the whole system or of one region."""
        M, K = (self.M, self.K) if region is None else self.parts[region]
        return float(0.5 * V @ (M @ V) + 0.5 * X @ (K @ X))

    def state(self, u, v) -> tuple[np.ndarray, np.ndarray]:
        """(X, V) from FE-only displacement and velocity fields u(x), v(x) (particles at rest)."""
        X, V = np.zeros(self.M.shape[0]), np.zeros(self.M.shape[0])
        xf = self.u_x[self.free]
        X[self.string.n:], V[self.string.n:] = u(xf), v(xf)
        return X, V


def rod_axial(rod: Rod1D, stiffness_share=None, mass_share=None, region=None):
    """(K_u, M_u, dofs) of the rod's axial field: stiffness and mass blocks (scipy CSR) with
    cell weights ``stiffness_share(x_mid)``, ``mass_share(x_mid)`` (default 1) times the
    indicator ``region(x_mid)``. Serial."""
    one = lambda xm: np.ones_like(xm)  # noqa: E731
    region = one if region is None else region
    wk, wm = (one if f is None else f for f in (stiffness_share, mass_share))
    rod.set_cell_weights("u", lambda xm: wk(xm) * region(xm))
    dofs = rod.field_dofs["u"][0]
    K, M = rod.K, rod.mass(lambda xm: wm(xm) * region(xm))
    return K[dofs][:, dofs].tocsr(), M[dofs][:, dofs].tocsr(), dofs


def axial_overlap(rod: Rod1D, string: SpringString, weighting: str = "ramp") -> AxialOverlap1D:
    """Couple the rod's axial field (left, ends at x_b) and the string (starts at x_a <= x_b).

    ``weighting`` sets the particles' shares of kinetic (r) and potential (q) energy, the FE
    taking the rest of each cell:

    * "ramp": both rise linearly from 0 at x_a to 1 at x_b (a step at x_a for x_a == x_b:
      the abrupt interface);
    * "volume": volume fractions (seed eq. 113, 119), the mass share from the particle
      segments ``[x - d/2, x + d/2]`` and the stiffness share from the springs between
      centres (the contact density the seed points to), both steps;
    * "volume_equal": the seed's simple choice q = r = particle volume fraction; the FE cell
      holding the first particle then loses stiffness the springs do not replace (a soft
      spot of d / 2).

    Serial.
    """
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {weighting!r}")
    x_a, x_b, d = string.x0, rod.x0 + rod.length, string.spacing
    if not rod.x0 < x_a <= x_b + 1e-12 < string.x[-1]:
        raise ValueError(f"the string must start inside the rod and end beyond it: rod "
                         f"[{rod.x0}, {x_b}], string [{x_a}, {string.x[-1]}]")
    ramp_k = ramp_m = (x_a, x_b)
    if weighting != "ramp":
        ramp_m = (x_a - d / 2, x_a - d / 2)
        ramp_k = ramp_m if weighting == "volume_equal" else (x_a, x_a)
    h = rod.length / rod.mesh.topology.index_map(1).size_local
    k_fe = lambda xm: 1.0 - particle_share(xm - h / 2, xm + h / 2, *ramp_k)  # noqa: E731
    m_fe = lambda xm: 1.0 - particle_share(xm - h / 2, xm + h / 2, *ramp_m)  # noqa: E731
    xp = string.x
    p_share = particle_share(xp - d / 2, xp + d / 2, *ramp_m)
    xs = 0.5 * (xp[:-1] + xp[1:])
    s_share = particle_share(xp[:-1], xp[1:], *ramp_k)

    dofs = rod.field_dofs["u"][0]
    ux = rod.field_dofs["u"][1]
    eps = 1e-9 * h
    pres = np.flatnonzero(ux >= x_a - eps)
    free = np.flatnonzero(ux < x_a - eps)
    under = np.flatnonzero(xp <= x_b + eps)
    N = FieldBasis.build(rod.V, xp[under, None], sub=0).local.toarray()[:, dofs]
    Np, Nd = N[:, pres], N[:, free]
    P = np.linalg.solve(Np.T @ Np, Np.T)  # eq. 79-90
    n = string.n
    T = np.zeros((ux.size, n + free.size))
    T[free, n + np.arange(free.size)] = 1.0
    T[np.ix_(pres, under)] = P
    T[np.ix_(pres, n + np.arange(free.size))] = -P @ Nd
    T = sp.csr_matrix(T)
    S = sp.hstack([sp.eye(n), sp.csr_matrix((n, free.size))]).tocsr()

    bins = {"fe": lambda x: x < x_a - eps, "overlap": lambda x: (x >= x_a - eps) & (x <= x_b + eps),
            "de": lambda x: x > x_b + eps}
    parts, M, K = {}, 0, 0
    for name, inside in bins.items():
        Kf, Mf, _ = rod_axial(rod, k_fe, m_fe, lambda xm, f=inside: f(xm).astype(float))
        Md = string.mass_matrix(p_share * inside(xp))
        Kd = string.stiffness_matrix(s_share * inside(xs))
        parts[name] = (S.T @ Md @ S + T.T @ Mf @ T, S.T @ Kd @ S + T.T @ Kf @ T)
        M, K = M + parts[name][0], K + parts[name][1]
    return AxialOverlap1D(rod, string, T, M.tocsr(), K.tocsr(), parts, x_a, x_b, ux, free)


class AverageAcceleration:
    """Newmark average acceleration (beta = 1/4, gamma = 1/2) for ``M X'' + K X = 0``.

    Unconditionally stable, no numerical damping, and it conserves
    ``V^T M V / 2 + X^T K X / 2`` exactly for symmetric M, K (to the solver's round-off).
    The effective matrix ``M + dt^2 / 4 K`` is factorised once.
    """

    def __init__(self, M: sp.spmatrix, K: sp.spmatrix, dt: float):
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"AverageAcceleration.dt must be > 0 in s, got {dt!r}")
        self.K, self.dt = K.tocsr(), dt
        self._lu = spla.splu((M + dt**2 / 4 * K).tocsc())
        self._M_lu = spla.splu(M.tocsc())

    def initial_acceleration(self, X: np.ndarray) -> np.ndarray:
        return -self._M_lu.solve(self.K @ X)

    def step(self, X, V, A):
        """(X, V, A) one step later."""
        dt = self.dt
        A1 = self._lu.solve(-(self.K @ (X + dt * V + dt**2 / 4 * A)))
        return X + dt * V + dt**2 / 4 * (A + A1), V + dt / 2 * (A + A1), A1
