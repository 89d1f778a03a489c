"""UFL forms of linear isotropic micropolar elasticity (seed 001 eq. 1-7).

The material is a strain-energy function of the micropolar strain
``eps_ij = u_i,j + e_ijk phi_k`` and the curvature ``kap_ij = phi_i,j``; stresses are its
derivatives (``ufl.diff``), so changing the material touches one function. Constants
live in ``fem.Constant`` so load stepping or parameter sweeps never recompile forms.
"""

from __future__ import annotations

from dataclasses import dataclass

import dolfinx_solver  # noqa: F401

import numpy as np
import ufl
from dolfinx import default_scalar_type, fem

from granfe.materials import MicropolarMaterial

__all__ = [
    "MaterialConstants",
    "strain",
    "curvature",
    "strain_energy_density",
    "stresses",
    "internal_work",
    "inertia_work",
    "kinetic_energy_density",
]


@dataclass(frozen=True)
class MaterialConstants:
    """The moduli of a :class:`MicropolarMaterial` as ``fem.Constant`` on a mesh."""

    lam: fem.Constant
    mu: fem.Constant
    kappa: fem.Constant
    alpha: fem.Constant
    beta: fem.Constant
    gamma: fem.Constant
    rho: fem.Constant
    rho_j: fem.Constant

    @classmethod
    def from_material(cls, domain, material: MicropolarMaterial) -> MaterialConstants:
        def c(value):
            return fem.Constant(domain, default_scalar_type(value))

        m = material
        return cls(c(m.lam), c(m.mu), c(m.kappa), c(m.alpha), c(m.beta), c(m.gamma),
                   c(m.rho), c(m.rho * m.j))

    def update(self, material: MicropolarMaterial) -> None:
        """Change the moduli in place (no form recompilation)."""
        m = material
        for name, value in (("lam", m.lam), ("mu", m.mu), ("kappa", m.kappa), ("alpha", m.alpha),
                            ("beta", m.beta), ("gamma", m.gamma), ("rho", m.rho),
                            ("rho_j", m.rho * m.j)):
            getattr(self, name).value = value


def _spin(phi, gdim: int):
    """``e_ijk phi_k``: the skew tensor of the micro-rotation (phi scalar phi_z in 2D)."""
    if gdim == 2:
        return ufl.as_matrix([[0, phi], [-phi, 0]])
    return ufl.as_matrix([[0, phi[2], -phi[1]], [-phi[2], 0, phi[0]], [phi[1], -phi[0], 0]])


def strain(u, phi):
    """Micropolar (unsymmetric) strain ``eps_ij = u_i,j + e_ijk phi_k``."""
    gdim = ufl.shape(u)[0]
    return ufl.grad(u) + _spin(phi, gdim)


def curvature(phi):
    """Curvature (wryness) ``kap_ij = phi_i,j``; in 2D the vector ``phi_z,j``."""
    return ufl.grad(phi)


def strain_energy_density(eps, kap, c: MaterialConstants):
    """Isotropic micropolar energy per unit volume (Eringen 1999 eq. 5.1.5).

    ``W = lam/2 (tr eps)^2 + (mu + kappa)/2 eps:eps + mu/2 eps:eps^T
        + alpha/2 (tr kap)^2 + beta/2 kap:kap^T + gamma/2 kap:kap``,
    so that ``sigma = lam tr(eps) I + (2 mu + kappa) sym(eps) + kappa skw(eps)`` and
    ``m = alpha tr(kap) I + beta kap^T + gamma kap``. In 2D ``kap`` is a vector and only
    gamma enters.
    """
    W = (c.lam / 2 * ufl.tr(eps) ** 2 + (c.mu + c.kappa) / 2 * ufl.inner(eps, eps)
         + c.mu / 2 * ufl.inner(eps, eps.T))
    if len(ufl.shape(kap)) == 1:
        return W + c.gamma / 2 * ufl.inner(kap, kap)
    return W + (c.alpha / 2 * ufl.tr(kap) ** 2 + c.beta / 2 * ufl.inner(kap, kap.T)
                + c.gamma / 2 * ufl.inner(kap, kap))


def stresses(u, phi, c: MaterialConstants):
    """Force stress sigma (unsymmetric) and couple stress m as UFL expressions."""
    eps = ufl.variable(strain(u, phi))
    kap = ufl.variable(curvature(phi))
    W = strain_energy_density(eps, kap, c)
    return ufl.diff(W, eps), ufl.diff(W, kap)


def internal_work(u, phi, du, dphi, c: MaterialConstants):
    """Internal virtual work density ``sigma : d eps + m : d kap``."""
    sigma, m = stresses(u, phi, c)
    return ufl.inner(sigma, strain(du, dphi)) + ufl.inner(m, curvature(dphi))


def inertia_work(a_u, a_phi, du, dphi, c: MaterialConstants):
    """Inertial virtual work density ``rho a_u . du + rho j a_phi . dphi``."""
    return c.rho * ufl.inner(a_u, du) + c.rho_j * ufl.inner(a_phi, dphi)


def kinetic_energy_density(v_u, v_phi, c: MaterialConstants):
    """``rho |v|^2 / 2 + rho j |omega|^2 / 2``."""
    return c.rho / 2 * ufl.inner(v_u, v_u) + c.rho_j / 2 * ufl.inner(v_phi, v_phi)


def zero_vector(domain, n: int) -> fem.Constant:
    """A vector ``fem.Constant`` of zeros (length n), e.g. an initial traction."""
    return fem.Constant(domain, np.zeros(n, dtype=default_scalar_type))
