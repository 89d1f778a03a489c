"""Classical elasticity softened by the largest strain reached: the smallest model with
history, the seam's own check (and a template for plastic and damage models).

Fields: the displacement ``u`` only. With ``eps = sym grad u`` and the history variable
``k`` (the largest ``|eps|`` reached so far), the stress is secant-softened,
``sigma = C : eps / (1 + s k)``, ``k_trial = max(k_committed, |eps|)``: loading beyond
``k`` softens the material, unloading and reloading below it follow the secant line of
the largest strain reached. The update is closed form, so the residual is UFL throughout
and SNES gets the consistent tangent from ``ufl.derivative``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import dolfinx_solver  # noqa: F401

import numpy as np
import ufl

from granfe.models.base import ContinuumModel, Field

__all__ = ["StrainMemoryMaterial", "StrainMemory"]


@dataclass(frozen=True)
class StrainMemoryMaterial:
    """Lame constants lam, mu [Pa], softening s [-] (per unit strain), density rho [kg/m^3]."""

    lam: float
    mu: float
    softening: float = 0.0
    rho: float = 1.0

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"StrainMemoryMaterial.{f.name} must be a finite number, got {v!r}")
        for name, ok, rule in (("mu", self.mu > 0, "mu > 0"),
                               ("lam", 3 * self.lam + 2 * self.mu > 0, "3 lam + 2 mu > 0"),
                               ("softening", self.softening >= 0, "softening >= 0"),
                               ("rho", self.rho > 0, "rho > 0")):
            if not ok:
                raise ValueError(f"StrainMemoryMaterial.{name} = {getattr(self, name)!r} "
                                 f"violates {rule}")


class StrainMemory(ContinuumModel):
    """Secant-softened classical elasticity remembering its largest strain (field u)."""

    name = "strain_memory"
    linear = False
    material_type = StrainMemoryMaterial

    def fields(self, gdim):
        return (Field("u", (gdim,), tuple(f"u_{a}" for a in "xyz"[:gdim]), 1),)

    def constant_values(self, material):
        return {"lam": material.lam, "mu": material.mu, "s": material.softening,
                "rho": material.rho}

    def state_variables(self, gdim):
        return {"max_strain": ()}

    @staticmethod
    def _eps(u):
        return ufl.sym(ufl.grad(u))

    def state_update(self, w, state):
        eps = self._eps(w[0])
        # sqrt(x + tiny): |eps| is not differentiable at 0 and the Newton tangent at an
        # unstrained start would be NaN
        return {"max_strain": ufl.max_value(state["max_strain"], ufl.sqrt(ufl.inner(eps, eps) + 1e-30))}

    def _sigma(self, w, state):
        c = self.constants
        eps = self._eps(w[0])
        k = self.state_update(w, state)["max_strain"]
        gdim = ufl.shape(w[0])[0]
        return (c.lam * ufl.tr(eps) * ufl.Identity(gdim) + 2 * c.mu * eps) / (1 + c.s * k)

    def internal_work(self, w, dw, state):
        return ufl.inner(self._sigma(w, state), self._eps(dw[0]))

    def inertia_work(self, a, dw):
        return self.constants.rho * ufl.inner(a[0], dw[0])

    def kinetic_energy(self, v):
        return self.constants.rho / 2 * ufl.inner(v[0], v[0])

    def stored_energy(self, w, state):
        return ufl.inner(self._sigma(w, state), self._eps(w[0])) / 2

    def stresses(self, w, state):
        return {"sigma": self._sigma(w, state)}

    def rigid_modes(self, gdim):
        def translation(k):
            return lambda x: np.vstack([np.full(x.shape[1], float(i == k)) for i in range(gdim)])

        modes = [(translation(k),) for k in range(gdim)]
        if gdim == 2:
            modes.append((lambda x: np.vstack([-x[1], x[0]]),))
        else:
            for k in range(3):
                e = np.eye(3)[k]
                modes.append((lambda x, e=e: np.cross(e[:, None], x[:3], axis=0),))
        return modes
