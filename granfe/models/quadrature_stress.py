"""Small-strain continuum whose stress and tangent at each quadrature point are filled from
outside: the macro side of a two-scale (FE x RVE) computation (seed 004 eq. 13, 19, 23).

Field: the displacement ``u``. Three quadrature-point variables, in Mandel vectors
(``(xx, yy, sqrt2 xy)`` in 2D plane strain, ``(xx, yy, zz, sqrt2 yz, sqrt2 xz, sqrt2 xy)``
in 3D, as `dem.rve` writes them, so that ``sigma : eps = s . e``):

- ``stress`` S (k,) [Pa]: the stress a material point answered at the strain ``strain``;
- ``strain`` E (k,): the strain at which it was evaluated;
- ``tangent`` C (k, k) [Pa]: d sigma / d eps there (any approximation; it is only the
  Newton matrix).

The stress of the fields is the first-order expansion about the evaluation point::

    sigma(u) = S + C (e(u) - E),      e(u) = mandel(sym grad u),

so wherever the filler has just evaluated the points at the current fields (E = e(u) at
every quadrature point), the residual is exactly that of the filled stress S, and
``ufl.derivative`` gives the Jacobian ``C`` without any knowledge of the material. Filled
once (E = 0, S = 0, C an elasticity tensor) the model is linear elasticity.

The model keeps the variables as its quadrature-point state (so a checkpoint of the
problem carries them), but never updates them itself: the trial state is the committed
one. Whoever fills them calls :func:`fill` after every evaluation. Plane strain: the out-of-
plane stress is not represented (a 2D material point has none to give).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import dolfinx_solver  # noqa: F401

import numpy as np
import ufl

from granfe.models.base import ContinuumModel, Field
from granfe.models.strain_memory import StrainMemory

__all__ = ["QuadratureStress", "QuadratureStressMaterial", "elastic_tangent", "fill", "mandel",
           "mandel_size"]

SQ2 = math.sqrt(2.0)


@dataclass(frozen=True)
class QuadratureStressMaterial:
    """Density rho [kg/m^3] (> 0): the only constant; the rest is filled at the points."""

    rho: float = 1.0

    def __post_init__(self):
        if not (isinstance(self.rho, (int, float)) and math.isfinite(self.rho) and self.rho > 0):
            raise ValueError(f"QuadratureStressMaterial.rho must be > 0 kg/m^3, got {self.rho!r}")


def mandel_size(gdim: int) -> int:
    """Length k of a Mandel vector: 3 in 2D, 6 in 3D."""
    return {2: 3, 3: 6}[gdim]


def mandel(t):
    """Mandel vector (UFL, (k,)) of a symmetric gdim x gdim tensor (UFL)."""
    if ufl.shape(t)[0] == 2:
        return ufl.as_vector([t[0, 0], t[1, 1], SQ2 * t[0, 1]])
    return ufl.as_vector([t[0, 0], t[1, 1], t[2, 2], SQ2 * t[1, 2], SQ2 * t[0, 2], SQ2 * t[0, 1]])


def _tensor(v, gdim):
    """Symmetric gdim x gdim tensor (UFL) of a Mandel vector (UFL)."""
    if gdim == 2:
        return ufl.as_matrix([[v[0], v[2] / SQ2], [v[2] / SQ2, v[1]]])
    return ufl.as_matrix([[v[0], v[5] / SQ2, v[4] / SQ2],
                          [v[5] / SQ2, v[1], v[3] / SQ2],
                          [v[4] / SQ2, v[3] / SQ2, v[2]]])


def elastic_tangent(lam: float, mu: float, gdim: int) -> np.ndarray:
    """Mandel (k, k) [Pa] of isotropic elasticity (plane strain in 2D)."""
    k, nd = mandel_size(gdim), gdim
    c = 2.0 * mu * np.eye(k)
    c[:nd, :nd] += lam
    return c


def fill(state, name: str, owned: np.ndarray) -> None:
    """Write the owned points' values of variable ``name`` (flat, or (points, ...) shaped)
    into a problem's :class:`~granfe.state.QuadratureState` (committed and trial alike) and
    refresh the ghost cells from their owners. Collective (the scatter)."""
    f = state.committed[name]
    n = len(state.owned(name))
    values = np.asarray(owned, float).reshape(-1)
    if values.shape != (n,):
        raise ValueError(f"fill {name!r}: {values.size} values for {n} owned entries")
    f.x.array[:n] = values
    f.x.scatter_forward()
    state.trial[name].x.array[:] = f.x.array


class QuadratureStress(ContinuumModel):
    """Displacement field with the stress of filled quadrature points (module docstring)."""

    name = "quadrature_stress"
    linear = False
    material_type = QuadratureStressMaterial
    # a step starts from a converged state whose residual is only the boundary increment
    # (as for the plastic model): no divergence test, no line search
    solver_options = {"snes_divergence_tolerance": 1e300, "snes_linesearch_type": "none"}
    rigid_modes = StrainMemory.rigid_modes

    def fields(self, gdim):
        return (Field("u", (gdim,), tuple(f"u_{a}" for a in "xyz"[:gdim]), 1),)

    def constant_values(self, material):
        return {"rho": material.rho}

    def state_variables(self, gdim):
        k = mandel_size(gdim)
        return {"stress": (k,), "strain": (k,), "tangent": (k, k)}

    def state_update(self, w, state):
        return {name: state[name] for name in ("stress", "strain", "tangent")}

    @staticmethod
    def strain(u):
        """Mandel strain e(u) (UFL)."""
        return mandel(ufl.sym(ufl.grad(u)))

    def _sigma(self, w, state):
        e = self.strain(w[0])
        return state["stress"] + ufl.dot(state["tangent"], e - state["strain"])

    def internal_work(self, w, dw, state):
        return ufl.dot(self._sigma(w, state), self.strain(dw[0]))

    def inertia_work(self, a, dw):
        return self.constants.rho * ufl.inner(a[0], dw[0])

    def kinetic_energy(self, v):
        return self.constants.rho / 2 * ufl.inner(v[0], v[0])

    def stored_energy(self, w, state):
        """The work of the linearised stress from the evaluation point (the material's own
        energy is not known here)."""
        e = self.strain(w[0]) - state["strain"]
        return ufl.dot(state["stress"], e) + ufl.dot(e, ufl.dot(state["tangent"], e)) / 2

    def stresses(self, w, state):
        return {"sigma": _tensor(self._sigma(w, state), ufl.shape(w[0])[0])}
