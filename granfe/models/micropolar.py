"""Linear isotropic micropolar (Cosserat) elasticity, seed 001 eq. 1-7.

Fields: displacement ``u`` and micro-rotation ``phi`` (2D plane strain: the scalar
``phi_z``; 3D: a 3-vector). The material is a strain-energy function of the micropolar
strain ``eps_ij = u_i,j + e_ijk phi_k`` and the curvature ``kap_ij = phi_i,j``; stresses
are its derivatives (``ufl.diff``), so changing the material touches one function.

Index convention: ``sigma_ij = dW / d eps_ij`` is work-conjugate to ``u_i,j``, so the
traction on a face of unit normal n is ``t_i = sigma_ij n_j`` (the second index names the
face); likewise the surface couple is ``m_ij n_j``. In 2D the couple stress is the vector
``m_j = m_zj`` (conjugate to ``phi_z,j``), shape (2,).
"""

from __future__ import annotations

from dataclasses import dataclass

import dolfinx_solver  # noqa: F401

import numpy as np
import ufl
from dolfinx import default_scalar_type, fem

from granfe.materials import MicropolarMaterial
from granfe.models.base import ContinuumModel, Field

__all__ = [
    "Micropolar",
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

    @staticmethod
    def values(material: MicropolarMaterial) -> dict[str, float]:
        m = material
        return {"lam": m.lam, "mu": m.mu, "kappa": m.kappa, "alpha": m.alpha, "beta": m.beta,
                "gamma": m.gamma, "rho": m.rho, "rho_j": m.rho * m.j}

    @classmethod
    def from_material(cls, domain, material: MicropolarMaterial) -> MaterialConstants:
        return cls(**{k: fem.Constant(domain, default_scalar_type(v))
                      for k, v in cls.values(material).items()})

    def update(self, material: MicropolarMaterial) -> None:
        """Change the moduli in place (no form recompilation)."""
        for name, value in self.values(material).items():
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
    """Force stress sigma (unsymmetric, ``t_i = sigma_ij n_j``) and couple stress m."""
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


class Micropolar(ContinuumModel):
    """Linear isotropic micropolar elasticity with a :class:`MicropolarMaterial`."""

    name = "micropolar"
    linear = True
    material_type = MicropolarMaterial

    @staticmethod
    def fields(gdim):
        axes = "xyz"[:gdim]
        if gdim == 2:
            phi = Field("phi", (), ("phi_z",), 1)   # plane strain: phi_z only
        else:
            phi = Field("phi", (3,), ("phi_x", "phi_y", "phi_z"), 1)
        return (Field("u", (gdim,), tuple(f"u_{a}" for a in axes), 2), phi)

    def make_constants(self, domain):
        return MaterialConstants.from_material(domain, self.material)

    def constant_values(self, material):
        return MaterialConstants.values(material)

    def internal_work(self, w, dw, state):
        return internal_work(*w, *dw, self.constants)

    def inertia_work(self, a, dw):
        return inertia_work(*a, *dw, self.constants)

    def kinetic_energy(self, v):
        return kinetic_energy_density(*v, self.constants)

    def stored_energy(self, w, state):
        u, phi = w
        return strain_energy_density(strain(u, phi), curvature(phi), self.constants)

    def stresses(self, w, state):
        sigma, m = stresses(*w, self.constants)
        return {"sigma": sigma, "couple_stress": m}

    @staticmethod
    def rigid_modes(gdim):
        """Translations (u = e_k, phi = 0) and rotations (u = e_k x x, phi = e_k)."""
        def translation(k):
            return lambda x: np.vstack([np.full(x.shape[1], float(i == k)) for i in range(gdim)])

        modes = [(translation(k), None) for k in range(gdim)]
        if gdim == 2:
            modes.append((lambda x: np.vstack([-x[1], x[0]]), lambda x: np.ones(x.shape[1])))
        else:
            for k in range(3):
                e = np.eye(3)[k]
                modes.append((lambda x, e=e: np.cross(e[:, None], x[:3], axis=0),
                              lambda x, e=e: np.tile(e[:, None], x.shape[1])))
        return modes

    def plot_fields(self, w, state):
        u, phi = w
        stress = self.stresses(w, state)
        sigma, m = stress["sigma"], stress["couple_stress"]
        gdim = self.gdim
        s = ufl.sym(sigma)
        dev = s - ufl.tr(s) / gdim * ufl.Identity(gdim)
        out = {
            "u_magnitude": ufl.sqrt(ufl.inner(u, u)),
            "von_mises": ufl.sqrt(1.5 * ufl.inner(dev, dev)),
            "couple_stress_magnitude": ufl.sqrt(ufl.inner(m, m)),
            "phi_z": phi if gdim == 2 else phi[2],
        }
        axes = "xyz"
        for i in range(gdim):
            out[f"u_{axes[i]}"] = u[i]
            for j in range(gdim):
                out[f"sigma_{axes[i]}{axes[j]}"] = sigma[i, j]
        if gdim == 2:
            out["m_zx"], out["m_zy"] = m[0], m[1]
        return out
