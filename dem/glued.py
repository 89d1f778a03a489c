"""A string of glued Hertz-Mindlin elastic spheres, quasi-static (seed 001 §2.3, eq. 60-67).

Spheres of radius R sit on the x axis, touching; each carries 2D dofs (u, v, theta)
[m, m, rad] in the global vector ``q`` (3 n,) as ``q[3 i + k]``. For the contact c between
spheres alpha = i (left) and beta = i + 1 (right):

* normal (eq. 60): ``delta_n = u_a - u_b`` (compression > 0),
  ``f_x = 4/3 E0 sqrt(R0) delta_n^(3/2)``, ``E0 = E / (2 (1 - nu^2))``, ``R0 = R / 2``;
* tangential, Mindlin (eq. 61): ``a = sqrt(R0 delta_n)``,
  ``delta_t = v_a - v_b + R (theta_a + theta_b)``, ``f_y = 4 mu / (2 - nu) a delta_t``
  with ``mu = E / (2 (1 + nu))``;
* contact moment (eq. 66): ``f_th = B 4 mu / (2 - nu) a R^2 (theta_a + theta_b) + R f_y``;
  the factor B adds a rotational stiffness so that the moment rows are not multiples of
  the ``f_y`` rows (a rank-deficient tangent otherwise);
* element vector (eq. 62): ``[f_x, f_y, f_th, -f_x, -f_y, f_th]`` on
  ``[u_a, v_a, th_a, u_b, v_b, th_b]``; tangent eq. 63-65 below.

Reconstruction notes (the OCR of eq. 60-66 is garbled): the moduli follow from the
visible ``4 mu``, ``(2 - nu)`` and the tangent of eq. 64-65; we write the B term with
``R^2`` so that B is dimensionless, as the seed calls it. The spheres are *glued*: in
tension (``delta_n < 0``) we use ``sign(delta_n) |delta_n|^(3/2)`` and ``a = sqrt(R0
|delta_n|)``, a symmetric bond. At ``delta_n = 0`` the Hertz tangent vanishes, so a
solve must start from a compressed state (:meth:`GluedString.axial_predictor`), as in
the seed, which loads axially first "to generate a transverse stiffness".
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

__all__ = ["GluedLaw", "GluedString", "NewtonDidNotConverge", "NewtonReport", "SpringString",
           "newton"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GluedLaw:
    """Glued Hertz-Mindlin contact between equal spheres (seed 001 eq. 60-66).

    Attributes: E Young's modulus [Pa] (> 0), nu Poisson's ratio (in (-1, 0.5)),
    radius R [m] (> 0), B dimensionless rotational factor (>= 0).
    """

    E: float
    nu: float
    radius: float
    B: float = 50.0

    def __post_init__(self):
        if not (np.isfinite(self.E) and self.E > 0):
            raise ValueError(f"GluedLaw.E must be > 0 in Pa, got {self.E!r}")
        if not (-1.0 < self.nu < 0.5):
            raise ValueError(f"GluedLaw.nu must lie in (-1, 0.5), got {self.nu!r}")
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"GluedLaw.radius must be > 0 in m, got {self.radius!r}")
        if not (np.isfinite(self.B) and self.B >= 0):
            raise ValueError(f"GluedLaw.B must be >= 0, got {self.B!r}")

    @property
    def k_hertz(self) -> float:
        """``4/3 E0 sqrt(R0)`` [N m^-3/2]."""
        return 4.0 / 3.0 * self.E / (2 * (1 - self.nu**2)) * np.sqrt(self.radius / 2)

    @property
    def k_mindlin(self) -> float:
        """``4 mu / (2 - nu)`` [Pa]: f_y = k_mindlin a delta_t."""
        return 4.0 * self.E / (2 * (1 + self.nu)) / (2 - self.nu)


def _kinematics(q: np.ndarray, R: float, R0: float):
    """Per contact (n - 1,): delta_n, |delta_n|, a, delta_t, sum of rotations."""
    Q = q.reshape(-1, 3)
    dn = Q[:-1, 0] - Q[1:, 0]
    th = Q[:-1, 2] + Q[1:, 2]
    dt = Q[:-1, 1] - Q[1:, 1] + R * th
    return dn, np.abs(dn), np.sqrt(R0 * np.abs(dn)), dt, th


class GluedString:
    """n glued spheres of a :class:`GluedLaw`, centres at ``x0 + 2 R i`` (seed 001 §2.3)."""

    def __init__(self, n_spheres: int, law: GluedLaw, x0: float = 0.0):
        if int(n_spheres) != n_spheres or n_spheres < 2:
            raise ValueError(f"GluedString.n_spheres must be an integer >= 2, got {n_spheres!r}")
        self.n, self.law = int(n_spheres), law
        self.x = x0 + 2 * law.radius * np.arange(self.n)
        self.n_dofs = 3 * self.n

    def contact_forces(self, q: np.ndarray) -> np.ndarray:
        """(n - 1, 3): f_x [N], f_y [N], f_th [N m] per contact (eq. 60, 61, 66)."""
        law, R = self.law, self.law.radius
        dn, adn, a, dt, th = _kinematics(q, R, R / 2)
        fx = law.k_hertz * np.sign(dn) * adn**1.5
        fy = law.k_mindlin * a * dt
        fth = law.B * law.k_mindlin * a * R**2 * th + R * fy
        return np.column_stack([fx, fy, fth])

    def f_int(self, q: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """Assembled internal force and moment vector F^INT(q) (3 n,) (eq. 62, 67).

        ``weights`` (n - 1, 3): optional row weights of (f_x, f_y, f_th) per contact.
        """
        f = self.contact_forces(q) if weights is None else self.contact_forces(q) * weights
        out = np.zeros((self.n, 3))
        out[:-1] += f
        out[1:] += f * np.array([-1.0, -1.0, 1.0])
        return out.ravel()

    def contact_tangents(self, q: np.ndarray) -> np.ndarray:
        """(n - 1, 6, 6) consistent tangents d f^INT,e / d q^e per contact (eq. 63-65)."""
        law, R, R0 = self.law, self.law.radius, self.law.radius / 2
        dn, adn, a, dt, th = _kinematics(q, R, R0)
        ddn = np.array([1.0, 0, 0, -1.0, 0, 0])
        ddt = np.array([0, 1.0, R, 0, -1.0, R])
        dth = np.array([0, 0, 1.0, 0, 0, 1.0])
        # d a / d delta_n = R0 sign / (2 a); zero at a = 0 where the Hertz law has no tangent
        da = np.divide(R0 * np.sign(dn), 2 * a, out=np.zeros_like(a), where=a > 0)[:, None]
        gx = 1.5 * law.k_hertz * np.sqrt(adn)[:, None] * ddn
        gy = law.k_mindlin * (da * dt[:, None] * ddn + a[:, None] * ddt)
        gth = law.B * law.k_mindlin * R**2 * (da * th[:, None] * ddn + a[:, None] * dth) + R * gy
        sign = np.array([1.0, 1.0, 1.0, -1.0, -1.0, 1.0])
        return sign[None, :, None] * np.stack([gx, gy, gth, gx, gy, gth], axis=1)

    def tangent(self, q: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """Consistent tangent dF^INT/dq (3 n, 3 n), dense (eq. 63-65).

        ``weights`` (n - 1, 3): optional row weights of (f_x, f_y, f_th) per contact.
        """
        ke = self.contact_tangents(q)
        if weights is not None:
            ke = ke * np.tile(weights, (1, 2))[:, :, None]
        K = np.zeros((self.n_dofs, self.n_dofs))
        for c in range(self.n - 1):
            K[3 * c:3 * c + 6, 3 * c:3 * c + 6] += ke[c]
        return K

    def axial_predictor(self, force: float, clamp: str = "right") -> np.ndarray:
        """Q (3 n,) of the string under an end axial force [N] (> 0 compresses), other end fixed.

        Every contact carries the same force, so ``delta_n = (F / k_hertz)^(2/3)`` each;
        the exact axial solution and the Newton start for any later load.
        """
        dn = np.sign(force) * (abs(force) / self.law.k_hertz) ** (2.0 / 3.0)
        k = np.arange(self.n)
        steps = (self.n - 1 - k) if clamp == "right" else -k
        q = np.zeros((self.n, 3))
        q[:, 0] = dn * steps
        return q.ravel()

    def clamp_dofs(self, end: str = "right") -> np.ndarray:
        """The three dofs of the end sphere ("left" or "right")."""
        i = self.n - 1 if end == "right" else 0
        return np.arange(3 * i, 3 * i + 3)

    def solve(self, f_ext: np.ndarray, fixed: np.ndarray, q0: np.ndarray, **kw) -> tuple:
        """Newton solve of R(q) = F^INT(q) - F^EXT = 0 (eq. 67) with ``q[fixed]`` held.

        Returns (q (3 n,), :class:`NewtonReport`); keywords go to :func:`newton`.
        """
        return newton(lambda q: (self.f_int(q) - f_ext, self.tangent(q)), q0, fixed,
                      scale=max(np.abs(f_ext).max(), 1.0), **kw)


@dataclass(frozen=True)
class SpringString:
    """Axial string of n particles joined by linear springs, for waves (linear dynamics).

    The long-wave speed is ``spacing * sqrt(stiffness / mass)``; with
    ``stiffness = C A / d`` and ``mass = rho A d`` it equals the rod's ``sqrt(C / rho)``.
    Dofs: the axial displacement u_i [m] of each particle, centres at ``x0 + spacing i``.

    Attributes: n (>= 2), spacing d [m], stiffness k [N/m], mass m [kg] (all > 0), x0 [m].
    """

    n: int
    spacing: float
    stiffness: float
    mass: float
    x0: float = 0.0

    def __post_init__(self):
        if int(self.n) != self.n or self.n < 2:
            raise ValueError(f"SpringString.n must be an integer >= 2, got {self.n!r}")
        for name in ("spacing", "stiffness", "mass"):
            val = getattr(self, name)
            if not (np.isfinite(val) and val > 0):
                raise ValueError(f"SpringString.{name} must be finite and > 0, got {val!r}")

    @property
    def x(self) -> np.ndarray:
        """(n,) particle centres [m]."""
        return self.x0 + self.spacing * np.arange(self.n)

    @property
    def wave_speed(self) -> float:
        """Long-wave (continuum-limit) speed [m/s]."""
        return self.spacing * np.sqrt(self.stiffness / self.mass)

    def stiffness_matrix(self, weights: np.ndarray | None = None) -> sp.csr_matrix:
        """K (n, n) with an optional potential-energy share per spring (n - 1,)."""
        w = np.ones(self.n - 1) if weights is None else np.asarray(weights, dtype=float)
        if w.shape != (self.n - 1,):
            raise ValueError(f"spring weights must have shape ({self.n - 1},), got {w.shape}")
        k = self.stiffness * w
        main = np.zeros(self.n)
        main[:-1] += k
        main[1:] += k
        return sp.diags([main, -k, -k], [0, -1, 1], format="csr")

    def mass_matrix(self, weights: np.ndarray | None = None) -> sp.csr_matrix:
        """Diagonal M (n, n) with an optional kinetic-energy share per particle (n,)."""
        w = np.ones(self.n) if weights is None else np.asarray(weights, dtype=float)
        if w.shape != (self.n,):
            raise ValueError(f"mass weights must have shape ({self.n},), got {w.shape}")
        return sp.diags(self.mass * w, format="csr")


class NewtonDidNotConverge(RuntimeError):
    """Newton-Raphson failed; ``iteration``, ``residual`` and the per-iteration ``history``."""

    def __init__(self, iteration: int, residual: float, history: list[float], why: str):
        self.iteration, self.residual, self.history = iteration, residual, history
        super().__init__(f"Newton did not converge at iteration {iteration}: relative residual "
                         f"{residual:.3e} ({why}); history {[f'{r:.2e}' for r in history]}")


@dataclass
class NewtonReport:
    """Relative residual norms per iteration (``history[0]`` is the start) and step lengths."""

    history: list[float] = field(default_factory=list)
    steps: list[float] = field(default_factory=list)

    @property
    def iterations(self) -> int:
        return len(self.history) - 1


def newton(fun: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], x0: np.ndarray,
           fixed: np.ndarray, *, scale: float = 1.0, rtol: float = 1e-10, max_it: int = 30,
           line_search: bool = True) -> tuple[np.ndarray, NewtonReport]:
    """Newton-Raphson with a backtracking (Armijo) line search on ||R|| / scale.

    ``fun(x) -> (R (n,), K (n, n))``; ``x[fixed]`` is held at its x0 value. Raises
    :class:`NewtonDidNotConverge` naming the iteration and residual.
    """
    x = np.array(x0, dtype=float)
    free = np.setdiff1d(np.arange(x.size), fixed)
    report = NewtonReport()
    r, K = fun(x)
    norm = np.linalg.norm(r[free]) / scale
    report.history.append(norm)
    for it in range(1, max_it + 1):
        if norm < rtol:
            return x, report
        Kff = K[np.ix_(free, free)]
        try:
            dx = -np.linalg.solve(Kff, r[free])
        except np.linalg.LinAlgError:
            raise NewtonDidNotConverge(it, norm, report.history, "singular tangent") from None
        alpha = 1.0
        while True:
            xt = x.copy()
            xt[free] += alpha * dx
            rt, Kt = fun(xt)
            nt = np.linalg.norm(rt[free]) / scale
            if not line_search or nt <= (1 - 1e-4 * alpha) * norm or alpha < 1e-6:
                break
            alpha *= 0.5
        if not np.isfinite(nt):
            raise NewtonDidNotConverge(it, nt, report.history, "non-finite residual")
        x, r, K, norm = xt, rt, Kt, nt
        report.history.append(norm)
        report.steps.append(alpha)
        log.info("newton it %d: |R|/scale = %.3e, step %.3g", it, norm, alpha)
    if norm < rtol:
        return x, report
    raise NewtonDidNotConverge(max_it, norm, report.history, f"max_it = {max_it} reached")
