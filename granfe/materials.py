"""Continuum material parameters.

A material is a frozen dataclass validated on construction; the UFL energy that
uses it lives in :mod:`granfe.forms`. Units are SI throughout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

__all__ = ["MicropolarMaterial", "lame_from_engineering"]


def lame_from_engineering(E: float, nu: float) -> tuple[float, float]:
    """Classical Lame constants (lam, mu) [Pa] from Young's modulus E [Pa] and Poisson's ratio nu."""
    if not (math.isfinite(E) and E > 0.0):
        raise ValueError(f"E (Young's modulus) must be a finite positive number in Pa, got {E!r}")
    if not (math.isfinite(nu) and -1.0 < nu < 0.5):
        raise ValueError(f"nu (Poisson's ratio) must lie in (-1, 0.5), got {nu!r}")
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    mu = E / (2.0 * (1.0 + nu))
    return lam, mu


@dataclass(frozen=True)
class MicropolarMaterial:
    """Isotropic linear micropolar (Cosserat) solid, seed 001 eq. 1-7.

    ``sigma_kl = lam eps_mm delta_kl + (2 mu + kappa) eps_kl + kappa e_klm (r_m - phi_m)``,
    ``m_kl = alpha phi_m,m delta_kl + beta phi_k,l + gamma phi_l,k``.

    Attributes:
        lam, mu: Lame constants [Pa].
        kappa: micropolar coupling modulus [Pa] (0 decouples the rotations).
        alpha, beta, gamma: couple-stress moduli [N] (= Pa m^2).
        rho: mass density [kg/m^3].
        j: micro-inertia per unit mass [m^2] (rotary inertia density is ``rho * j``).

    Construction checks Eringen's conditions for a non-negative strain energy of an
    isotropic micropolar solid (Eringen 1999, eq. 5.1.9): ``3 lam + 2 mu + kappa >= 0``,
    ``2 mu + kappa >= 0``, ``kappa >= 0``, ``3 alpha + beta + gamma >= 0``,
    ``gamma + beta >= 0``, ``gamma - beta >= 0``, with the first two and ``gamma + beta``
    strict (else a deformation costs no energy and no solve is possible). Eringen's ``mu``
    itself may be negative: with Forest's constants (``mu_c > mu_classical``) it is. The
    classical shear modulus is ``mu + kappa / 2``. ``kappa = 0`` is the classical limit
    (rotations decoupled). In plane strain only ``gamma`` enters the curvature energy.
    """

    lam: float
    mu: float
    kappa: float
    alpha: float = 0.0
    beta: float = 0.0
    gamma: float = 1.0
    rho: float = 1.0
    j: float = 1.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"MicropolarMaterial.{f.name} must be a finite number, got {value!r}")
        # (parameter blamed, quantity, rule, strict)
        checks = [
            ("mu", 2 * self.mu + self.kappa, "2 mu + kappa > 0", True),
            ("kappa", self.kappa, "kappa >= 0", False),
            ("lam", 3 * self.lam + 2 * self.mu + self.kappa, "3 lam + 2 mu + kappa > 0", True),
            ("gamma", self.gamma + self.beta, "gamma + beta > 0", True),
            ("beta", self.gamma - self.beta, "gamma - beta >= 0", False),
            ("alpha", 3 * self.alpha + self.beta + self.gamma, "3 alpha + beta + gamma >= 0", False),
            ("rho", self.rho, "rho > 0", True),
            ("j", self.j, "j > 0", True),
        ]
        for name, value, rule, strict in checks:
            if (value <= 0.0) if strict else (value < 0.0):
                raise ValueError(
                    f"MicropolarMaterial.{name} = {getattr(self, name)!r} violates {rule} "
                    f"(Eringen's conditions for a non-negative micropolar energy)"
                )

    @classmethod
    def from_engineering(
        cls,
        E: float,
        nu: float,
        *,
        length: float,
        kappa_over_mu: float | None = None,
        coupling_number: float | None = None,
        gamma_over_l2mu: float = 1.0,
        alpha_over_gamma: float = 0.0,
        beta_over_gamma: float = 0.0,
        rho: float = 1.0,
        j: float | None = None,
    ) -> MicropolarMaterial:
        """Material from engineering constants, the way seed 001 §2.2.5 states them.

        ``lam, mu`` are the classical Lame constants of (E, nu); ``kappa`` is given either
        as ``kappa_over_mu`` (seed 001: 0.1) or by the coupling number
        ``N = sqrt(kappa / (2 mu + kappa))`` in [0, 1) (Lakes); the couple modulus is
        ``gamma = gamma_over_l2mu * length**2 * mu`` (seed 001: 0.05 l^2 mu) with
        ``alpha, beta`` as fractions of gamma. ``j`` defaults to ``length**2``.
        """
        lam, mu = lame_from_engineering(E, nu)
        if (kappa_over_mu is None) == (coupling_number is None):
            raise ValueError("give exactly one of kappa_over_mu and coupling_number")
        if kappa_over_mu is not None:
            if not kappa_over_mu >= 0.0:
                raise ValueError(f"kappa_over_mu must be >= 0, got {kappa_over_mu!r}")
            kappa = kappa_over_mu * mu
        else:
            N = coupling_number
            if not (N is not None and 0.0 <= N < 1.0):
                raise ValueError(f"coupling_number N must lie in [0, 1), got {N!r}")
            kappa = 2.0 * mu * N**2 / (1.0 - N**2)
        if not (math.isfinite(length) and length > 0.0):
            raise ValueError(f"length (characteristic length) must be > 0 in m, got {length!r}")
        gamma = gamma_over_l2mu * length**2 * mu
        return cls(
            lam=lam,
            mu=mu,
            kappa=kappa,
            alpha=alpha_over_gamma * gamma,
            beta=beta_over_gamma * gamma,
            gamma=gamma,
            rho=rho,
            j=length**2 if j is None else j,
        )

    @property
    def E(self) -> float:
        """Classical Young's modulus of (lam, mu) [Pa]."""
        return self.mu * (3 * self.lam + 2 * self.mu) / (self.lam + self.mu)

    @property
    def nu(self) -> float:
        """Classical Poisson's ratio of (lam, mu)."""
        return self.lam / (2 * (self.lam + self.mu))

    @property
    def coupling_number(self) -> float:
        """Lakes' coupling number ``N = sqrt(kappa / (2 mu + kappa))``."""
        return math.sqrt(self.kappa / (2 * self.mu + self.kappa))

    @property
    def bending_length(self) -> float:
        """Plane characteristic length ``l_b = sqrt(gamma / (2 (2 mu + kappa)))`` [m] (Lakes)."""
        return math.sqrt(self.gamma / (2 * (2 * self.mu + self.kappa)))
