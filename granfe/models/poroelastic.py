"""Biot poroelasticity (u-p), quasi-static, backward Euler in time; plain or micropolar skeleton.

Fields: displacement ``u`` (and, for :class:`MicropolarPoroelastic`, the micro-rotation
``phi``) and the pore pressure ``p`` (Taylor-Hood by default: u of degree 2, p of degree 1).
Balance of momentum with the total stress ``sigma = sigma'(u) - alpha p I`` and balance of
fluid mass ``d zeta / dt + div q = 0`` with the fluid content ``zeta = alpha div u + p / M``
and Darcy's flux ``q = -(k / mu_f) grad p`` (Biot 1941; Coussy 2004 ch. 4; the fluid of seed
003 is the compressible-Darcy limit of the same balance). The fluid couples to the
volumetric strain only (the micro-rotation's spin is traceless), so a micropolar skeleton
keeps its couple stresses unchanged.

Time stepping lives in the quadrature-point state of the model contract: the committed
fluid content ``zeta_n`` is the only history, and one static solve of the residual

    (sigma'(u) : grad du - alpha p div du)
    + (zeta(u, p) - zeta_n) dp + dt (k / mu_f) grad p . grad dp  = external work

with the constant ``model.constants.dt`` is one backward-Euler step (driven by
:class:`granfe.consolidation.Consolidation`; not by :class:`granfe.dynamics.GeneralizedAlpha`:
the model has no inertia and is first order in time). The mass balance is multiplied by
``dt`` so that ``dt = 0`` is admissible: it is the undrained (instantaneous) response, with
the pressure ``p = -M alpha div u`` (Skempton's ``B`` under an isotropic load). A fluid
flux given as a surface load on ``p`` must be multiplied by ``dt`` too (the stepper does it).

The Biot coefficient's constant is ``biot_alpha`` (``alpha`` is a couple-stress modulus of the
micropolar skeleton). Sign conventions: tension positive, pressure positive in compression of the fluid; a
surface load on ``p`` is the fluid volume flux *into* the body per unit area [m/s] times dt.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import dolfinx_solver  # noqa: F401

import numpy as np
import ufl
from dolfinx import default_scalar_type, fem

from granfe.materials import MicropolarMaterial, lame_from_engineering
from granfe.models import micropolar as _mp
from granfe.models.base import ContinuumModel, Field

__all__ = ["PoreFluid", "PoroelasticMaterial", "MicropolarPoroelasticMaterial", "Poroelastic",
           "MicropolarPoroelastic", "effective_stress"]


def _finite(owner: str, name: str, value, allow_inf: bool = False) -> float:
    ok = isinstance(value, (int, float)) and not math.isnan(value) and (allow_inf or math.isfinite(value))
    if not ok:
        raise ValueError(f"{owner}.{name} must be a finite number, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class PoreFluid:
    """The pore fluid and its coupling to the skeleton (Biot's constants).

    Attributes:
        k: intrinsic permeability [m^2], >= 0 (0: undrained at every time).
        mu_f: dynamic viscosity of the fluid [Pa s], > 0 (water: 1e-3).
        alpha: Biot coefficient in (0, 1] (1: incompressible grains).
        M: Biot modulus [Pa], > 0; ``math.inf`` for incompressible grains and fluid
            (``1/M = n/K_f + (alpha - n)/K_s``, :meth:`from_constituents`).
    """

    k: float
    mu_f: float = 1.0e-3
    alpha: float = 1.0
    M: float = math.inf

    def __post_init__(self) -> None:
        for f in fields(self):
            _finite("PoreFluid", f.name, getattr(self, f.name), allow_inf=f.name == "M")
        if self.k < 0:
            raise ValueError(f"PoreFluid.k (intrinsic permeability) must be >= 0 m^2, got {self.k!r}")
        if not self.mu_f > 0:
            raise ValueError(f"PoreFluid.mu_f (fluid viscosity) must be > 0 Pa s, got {self.mu_f!r}")
        if not 0 < self.alpha <= 1:
            raise ValueError(f"PoreFluid.alpha (Biot coefficient) must lie in (0, 1], got {self.alpha!r}")
        if not self.M > 0:
            raise ValueError(f"PoreFluid.M (Biot modulus) must be > 0 Pa (inf allowed), got {self.M!r}")

    @classmethod
    def from_constituents(cls, *, k: float, mu_f: float, porosity: float, K_f: float,
                          K_drained: float, K_s: float = math.inf) -> PoreFluid:
        """Biot's constants from the porosity and the bulk moduli [Pa] of the fluid ``K_f``,
        the grains ``K_s`` (inf: incompressible) and the drained skeleton ``K_drained``:
        ``alpha = 1 - K_drained / K_s``, ``1/M = n / K_f + (alpha - n) / K_s``."""
        if not 0 < porosity < 1:
            raise ValueError(f"porosity must lie in (0, 1), got {porosity!r}")
        for name, value in (("K_f", K_f), ("K_drained", K_drained), ("K_s", K_s)):
            if not value > 0:
                raise ValueError(f"{name} (bulk modulus) must be > 0 Pa, got {value!r}")
        if not K_drained < K_s:
            raise ValueError(f"K_drained must be below K_s, got {K_drained!r} >= {K_s!r}")
        alpha = 1.0 - K_drained / K_s
        inv_M = porosity / K_f + (alpha - porosity) / K_s
        return cls(k=k, mu_f=mu_f, alpha=alpha, M=1.0 / inv_M)

    @property
    def mobility(self) -> float:
        """``k / mu_f`` [m^2 / (Pa s)]."""
        return self.k / self.mu_f

    @property
    def inv_M(self) -> float:
        """Storage coefficient at constant strain ``1/M`` [1/Pa]."""
        return 1.0 / self.M


class _PoroelasticConstantsMixin:
    """Derived constants of a drained skeleton of classical Lame constants (lam, mu)."""

    fluid: PoreFluid

    @property
    def _lame(self) -> tuple[float, float]:
        raise NotImplementedError

    @property
    def G(self) -> float:
        """Drained (classical) shear modulus [Pa]."""
        return self._lame[1]

    @property
    def K(self) -> float:
        """Drained bulk modulus ``lam + 2 mu / 3`` [Pa]."""
        lam, mu = self._lame
        return lam + 2 * mu / 3

    @property
    def K_u(self) -> float:
        """Undrained bulk modulus ``K + alpha^2 M`` [Pa] (inf for M = inf)."""
        return self.K + self.fluid.alpha**2 * self.fluid.M

    @property
    def B(self) -> float:
        """Skempton's coefficient ``alpha M / K_u``: pore pressure per isotropic total stress
        applied undrained."""
        f = self.fluid
        return 1.0 / f.alpha if math.isinf(f.M) else f.alpha * f.M / self.K_u

    @property
    def nu(self) -> float:
        """Drained Poisson's ratio."""
        lam, mu = self._lame
        return lam / (2 * (lam + mu))

    @property
    def nu_u(self) -> float:
        """Undrained Poisson's ratio ``(3 K_u - 2 G) / (2 (3 K_u + G))`` (1/2 for M = inf)."""
        _, G = self._lame
        if math.isinf(self.K_u):
            return 0.5
        return (3 * self.K_u - 2 * G) / (2 * (3 * self.K_u + G))

    @property
    def oedometric_modulus(self) -> float:
        """Drained constrained modulus ``lam + 2 mu`` [Pa]."""
        lam, mu = self._lame
        return lam + 2 * mu

    @property
    def c_oedometric(self) -> float:
        """Consolidation coefficient of uniaxial strain (Terzaghi)
        ``c = (k/mu_f) / (1/M + alpha^2 / (lam + 2 mu))`` [m^2/s]."""
        f = self.fluid
        return f.mobility / (f.inv_M + f.alpha**2 / self.oedometric_modulus)

    @property
    def c_mandel(self) -> float:
        """Consolidation coefficient of Mandel's problem (Cheng & Detournay 1988)
        ``c = 2 (k/mu_f) B^2 G (1 - nu) (1 + nu_u)^2 / (9 (1 - nu_u) (nu_u - nu))`` [m^2/s]."""
        _, G = self._lame
        nu, nu_u, B = self.nu, self.nu_u, self.B
        return (2 * self.fluid.mobility * B**2 * G * (1 - nu) * (1 + nu_u) ** 2
                / (9 * (1 - nu_u) * (nu_u - nu)))


@dataclass(frozen=True)
class PoroelasticMaterial(_PoroelasticConstantsMixin):
    """Isotropic linear poroelastic solid: drained Lame constants and a :class:`PoreFluid`.

    Attributes:
        lam, mu: drained Lame constants [Pa] (``mu > 0``, ``3 lam + 2 mu > 0``).
        fluid: the pore fluid and Biot's constants.
    """

    lam: float
    mu: float
    fluid: PoreFluid

    def __post_init__(self) -> None:
        lam = _finite("PoroelasticMaterial", "lam", self.lam)
        mu = _finite("PoroelasticMaterial", "mu", self.mu)
        if not mu > 0:
            raise ValueError(f"PoroelasticMaterial.mu (drained shear modulus) must be > 0 Pa, got {mu!r}")
        if not 3 * lam + 2 * mu > 0:
            raise ValueError(f"PoroelasticMaterial.lam = {lam!r} violates 3 lam + 2 mu > 0 "
                             f"(a positive drained bulk modulus)")
        if not isinstance(self.fluid, PoreFluid):
            raise TypeError(f"PoroelasticMaterial.fluid must be a PoreFluid, got {type(self.fluid).__name__}")

    @classmethod
    def from_engineering(cls, E: float, nu: float, fluid: PoreFluid) -> PoroelasticMaterial:
        """From the drained Young's modulus E [Pa] and Poisson's ratio nu."""
        lam, mu = lame_from_engineering(E, nu)
        return cls(lam=lam, mu=mu, fluid=fluid)

    @property
    def _lame(self):
        return self.lam, self.mu


@dataclass(frozen=True)
class MicropolarPoroelasticMaterial(_PoroelasticConstantsMixin):
    """A micropolar skeleton (:class:`MicropolarMaterial`) saturated by a :class:`PoreFluid`.
    The classical (drained) shear modulus is ``mu + kappa / 2``."""

    skeleton: MicropolarMaterial
    fluid: PoreFluid

    def __post_init__(self) -> None:
        if not isinstance(self.skeleton, MicropolarMaterial):
            raise TypeError(f"MicropolarPoroelasticMaterial.skeleton must be a MicropolarMaterial, "
                            f"got {type(self.skeleton).__name__}")
        if not isinstance(self.fluid, PoreFluid):
            raise TypeError(f"MicropolarPoroelasticMaterial.fluid must be a PoreFluid, "
                            f"got {type(self.fluid).__name__}")

    @property
    def _lame(self):
        s = self.skeleton
        return s.lam, s.mu + s.kappa / 2


# ---- weak form -------------------------------------------------------------------------------
def effective_stress(u, c):
    """Drained (Terzaghi effective) stress ``lam tr(eps) I + 2 mu eps`` of a classical skeleton."""
    eps = ufl.sym(ufl.grad(u))
    return c.lam * ufl.tr(eps) * ufl.Identity(ufl.shape(u)[0]) + 2 * c.mu * eps


def fluid_content(u, p, c):
    """Variation of the fluid volume per unit volume ``zeta = alpha div u + p / M``."""
    return c.biot_alpha * ufl.div(u) + c.inv_M * p


def fluid_work(u, p, du, dp, zeta_n, c):
    """The coupling in the momentum balance and the dt-scaled mass balance (backward Euler)."""
    return (-c.biot_alpha * p * ufl.div(du)
            + (fluid_content(u, p, c) - zeta_n) * dp
            + c.dt * c.mobility * ufl.inner(ufl.grad(p), ufl.grad(dp)))


def darcy_flux(p, c):
    """Darcy's volume flux ``-(k / mu_f) grad p`` [m/s]."""
    return -c.mobility * ufl.grad(p)


class _Biot(ContinuumModel):
    """What the plain and the micropolar Biot models share: the fluid, its history and the
    time-step constant. Subclasses give the skeleton (its fields before ``p``)."""

    linear = True
    # the residual is affine in the fields: one Newton step (one factorisation) is the solution.
    # A norm test after it would compare round-off with the (small) residual of the previous
    # step's fields and ask for a useless second iteration (seen: 2 per step)
    solver_options = {"snes_max_it": 1, "snes_convergence_test": "skip"}

    def make_constants(self, domain):
        from types import SimpleNamespace

        values = dict(self.constant_values(self.material), dt=0.0)
        return SimpleNamespace(**{k: fem.Constant(domain, default_scalar_type(v)) for k, v in values.items()})

    @staticmethod
    def fluid_values(fluid: PoreFluid) -> dict[str, float]:
        return {"biot_alpha": fluid.alpha, "inv_M": fluid.inv_M, "mobility": fluid.mobility}

    def state_variables(self, gdim):
        return {"fluid_content": ()}

    def state_update(self, w, state):
        return {"fluid_content": fluid_content(w[0], w[-1], self.constants)}

    def inertia_work(self, a, dw):
        raise NotImplementedError(f"the {self.name} model is quasi-static; step it with "
                                  f"granfe.consolidation.Consolidation")

    def kinetic_energy(self, v):
        raise NotImplementedError(f"the {self.name} model is quasi-static")

    def set_time_step(self, dt: float) -> None:
        """The backward-Euler step of the next solve [s]; 0 is the undrained response."""
        if not (np.isfinite(dt) and dt >= 0):
            raise ValueError(f"dt (time step) must be a finite number >= 0 s, got {dt!r}")
        self.constants.dt.value = dt

    def _fluid_stresses(self, w):
        return {"darcy_flux": darcy_flux(w[-1], self.constants)}


class Poroelastic(_Biot):
    """Biot's u-p poroelasticity on a classical linear elastic skeleton (fields u, p)."""

    name = "poroelastic"
    material_type = PoroelasticMaterial

    @staticmethod
    def fields(gdim):
        axes = "xyz"[:gdim]
        return (Field("u", (gdim,), tuple(f"u_{a}" for a in axes), 2), Field("p", (), (), 1))

    def constant_values(self, material):
        return {"lam": material.lam, "mu": material.mu, **self.fluid_values(material.fluid)}

    def internal_work(self, w, dw, state):
        (u, p), (du, dp) = w, dw
        c = self.constants
        return (ufl.inner(effective_stress(u, c), ufl.grad(du))
                + fluid_work(u, p, du, dp, state["fluid_content"], c))

    def stored_energy(self, w, state):
        u, p = w
        c = self.constants
        eps = ufl.sym(ufl.grad(u))
        return c.lam / 2 * ufl.tr(eps) ** 2 + c.mu * ufl.inner(eps, eps) + c.inv_M / 2 * p**2

    def stresses(self, w, state):
        u, p = w
        c = self.constants
        s = effective_stress(u, c)
        total = s - c.biot_alpha * p * ufl.Identity(self.gdim)
        return {"sigma": total, "effective_stress": s, **self._fluid_stresses(w)}

    @staticmethod
    def rigid_modes(gdim):
        """Rigid motions of u (p = 0): translations, then rotations about the origin."""
        return [(u, None) for u, _ in _mp.Micropolar.rigid_modes(gdim)]


class MicropolarPoroelastic(_Biot):
    """Biot poroelasticity on a micropolar skeleton (fields u, phi, p): the fluid sees the
    volumetric strain ``tr(eps) = div u``, the couple stresses are the skeleton's."""

    name = "micropolar_poroelastic"
    material_type = MicropolarPoroelasticMaterial

    @staticmethod
    def fields(gdim):
        return (*_mp.Micropolar.fields(gdim), Field("p", (), (), 1))

    def constant_values(self, material):
        return {**_mp.MaterialConstants.values(material.skeleton), **self.fluid_values(material.fluid)}

    def internal_work(self, w, dw, state):
        (u, phi, p), (du, dphi, dp) = w, dw
        c = self.constants
        return (_mp.internal_work(u, phi, du, dphi, c)
                + fluid_work(u, p, du, dp, state["fluid_content"], c))

    def stored_energy(self, w, state):
        u, phi, p = w
        c = self.constants
        return (_mp.strain_energy_density(_mp.strain(u, phi), _mp.curvature(phi), c)
                + c.inv_M / 2 * p**2)

    def stresses(self, w, state):
        u, phi, p = w
        c = self.constants
        s, m = _mp.stresses(u, phi, c)
        total = s - c.biot_alpha * p * ufl.Identity(self.gdim)
        return {"sigma": total, "couple_stress": m, "effective_stress": s, **self._fluid_stresses(w)}

    @staticmethod
    def rigid_modes(gdim):
        return [(*mode, None) for mode in _mp.Micropolar.rigid_modes(gdim)]
