"""Finite-strain isotropic micromorphic (Eringen-Mindlin) elasticity in the reference
configuration: the quadratic model of the open Tardigrade micromorphic linear elasticity
(Regueiro 2010; Miller's ``micromorphic_linear_elasticity``), solved with SNES.

Fields as in :mod:`granfe.models.micromorphic`: displacement ``u`` and micro-displacement
``phi = chi - I`` (2D plane strain: 4 in-plane components, 3D: 9), both functions of the
reference position X; every gradient below is the reference gradient ``d/dX``.

Deformation measures (Regueiro 2010; Tardigrade ``computeDeformationMeasures``)::

    F = I + grad u,   C = F^T F,   Psi = F^T chi,   Gamma_IJK = F_iI chi_iJ,K
    E = (C - I) / 2   (Green-Lagrange),   Etilde = Psi - I   (micro strain)

and the stored energy per unit reference volume, with the isotropic A, B, C, D of
:mod:`granfe.models.micromorphic` (the same 18 constants of a :class:`MicromorphicMaterial`,
whose Smith admissibility check therefore carries over unchanged: it is the positive
definiteness of the quadratic form in (E, Etilde, Gamma))::

    psi = E:A:E / 2 + Etilde:B:Etilde / 2 + Gamma:C:Gamma / 2 + E:D:Etilde

Its partial derivatives are ``psi_E = d psi / dE`` (symmetric), ``T = d psi / dEtilde`` and
``H = d psi / dGamma``. They are computed by the small-strain law itself (its energy is the
same quadratic form of (eps, E, G); :func:`energy_partials`), so the constants live in one
place.

Residual. The solid is hyperelastic: the internal virtual work is the first variation of
the stored energy, ``delta int psi dV`` over the reference volume. Since F, chi and grad chi
are linear in (u, phi), that variation is, exactly,
``P : grad du + Q : dphi + R : grad dphi`` with the nominal stresses
``P = d psi / dF``, ``Q = d psi / dchi``, ``R = d psi / d(grad chi)``, which
:meth:`MicromorphicFiniteStrain.internal_work` obtains by automatic differentiation
(``ufl.diff``) of psi; the Jacobian is the automatic derivative of that residual, so
Newton's method converges quadratically. By the chain rule::

    P_iJ = F_iI psi_E_IJ + chi_iK T_JK + chi_iL,K H_JLK,  Q_iJ = F_iI T_IJ,  R_iJK = F_iI H_IJK.

Stresses and index conventions (those of the small-strain module carried to the reference
configuration: in a second-order stress the second index names the face, in the
higher-order stress the last index names the face / the gradient direction):

* ``S`` [Pa], the (unsymmetric) second Piola-Kirchhoff stress, ``S = F^-1 P``::

      S_IJ = psi_E_IJ + (C^-1 Psi)_IK T_JK + (C^-1 Gamma)_IQR H_JQR;

  the nominal traction on a reference face of normal N is ``P N = F S N``;
* ``Sigma`` [Pa], the symmetric reference micro-stress,
  ``Sigma = psi_E + 2 sym(S - psi_E)``;
* ``M`` [Pa m], the reference higher-order stress, ``M_IJK = H_IJK = d psi / dGamma_IJK``.

They are Regueiro's (2010) pull-backs of Eringen's current stresses: with
``J = det F`` the current (Cauchy) stress ``sigma = F S F^T / J`` (traction
``sigma_ij n_j``), the micro-stress ``s = F Sigma F^T / J`` and the double stress
``m_ijk = F_iI chi_jJ F_kK M_IJK / J`` satisfy, for any motion, the power identity::

    d psi / dt = J [ sigma_ij (v_i,j - nu_ij) + s_ij nu_ij + m_ijk nu_ij,k ],   nu = chi' chi^-1

(spatial gradients), the finite-strain form of the small-strain virtual work
``sigma_ij du_i,j + (s_ij - sigma_ij) dphi_ij + m_ijk dphi_ij,k``; the tests check it
against complex-step derivatives of psi. In the small-strain limit S, Sigma, M tend to the
``sigma, s, m`` of :func:`granfe.models.micromorphic.micromorphic_stresses`.

Tardigrade's order: its ``PK2`` is ``S^T``, its ``referenceMicroStress`` is ``Sigma`` and
its ``referenceHigherOrderStress`` is ``M_T[I, J, K] = M[J, K, I]`` (first index the
gradient direction; :func:`to_tardigrade_order`). Its ``term1`` and ``term2`` are the
first two terms of ``S^T`` above. Its ``computeLinearElasticTerm3``, as read in the
tardigrade_hydra source (not run here), contracts ``M_T[I, Q, R] (C^-1 Gamma)[J, Q, R]``,
which pairs other indices of the higher-order stress than the energy-consistent
``M[I, Q, R] (C^-1 Gamma)[J, Q, R]`` used here: the two vanish with Gamma and differ at
second order in Gamma; ours satisfies the power identity to round-off (against a
complex-step derivative of psi), the other missed it by 4-9 % at random states with
entries of Gamma ~ 0.2-0.3.

Compilation: the 3D Jacobian is the dense Hessian of a quartic energy in the 45 field
derivatives, ~1e5 scalar operations in one basic block; gcc at dolfinx's default -O2 needs
many minutes for it, so the model declares ``jit_options`` (-O0) for whoever compiles its
forms (:attr:`MicromorphicFiniteStrain.jit_options`).
"""

from __future__ import annotations

from typing import ClassVar

import dolfinx_solver  # noqa: F401

import numpy as np
import ufl

from granfe.models.base import ContinuumModel
from granfe.models.micromorphic import (
    Micromorphic,
    MicromorphicMaterial,
    as_tensor_field,
    micromorphic_energy,
    micromorphic_stresses,
    plot_fields,
    strain_energy_density,
)

__all__ = [
    "MicromorphicFiniteStrain",
    "energy_density",
    "energy_partials",
    "finite_strain_measures",
    "micromorphic_finite_energy",
    "micromorphic_finite_nominal_stresses",
    "micromorphic_finite_stresses",
    "nominal_stresses",
    "push_forward",
    "to_tardigrade_order",
    "ufl_measures",
    "ufl_stresses",
]


# ---- the material-point law (numpy) ------------------------------------------------------

def _T(a):
    return np.swapaxes(a, -1, -2)


def finite_strain_measures(grad_u, chi, grad_chi):
    """``(F, E, Etilde, Gamma)`` at material points.

    Args:
        grad_u: ``grad_u[..., i, J] = u_i,J`` (reference gradient), shape (..., d, d).
        chi: the micro-deformation ``chi[..., i, J]``, shape (..., d, d).
        grad_chi: ``grad_chi[..., i, J, K] = chi_iJ,K``, shape (..., d, d, d).

    Returns:
        ``F = I + grad u``, ``E = (F^T F - I) / 2``, ``Etilde = F^T chi - I`` and
        ``Gamma[..., I, J, K] = F_iI chi_iJ,K``.
    """
    grad_u = np.asarray(grad_u, dtype=float)
    d = grad_u.shape[-1]
    eye = np.eye(d)
    F = eye + grad_u
    E = 0.5 * (_T(F) @ F - eye)
    Etilde = _T(F) @ np.asarray(chi, dtype=float) - eye
    Gamma = np.einsum("...iI,...iJK->...IJK", F, np.asarray(grad_chi, dtype=float))
    return F, E, Etilde, Gamma


def energy_partials(E, Etilde, Gamma, material: MicromorphicMaterial):
    """``(psi_E, T, H)``: the derivatives of psi with respect to E (symmetric), Etilde and
    Gamma, by the small-strain law of the same quadratic form.

    The small-strain energy is ``W(eps, E, G)`` with ``eps = sym(grad u)``,
    ``E = grad u^T + phi``; for ``grad u = E_green`` (symmetric) and
    ``phi = Etilde - E_green`` its arguments are (E_green, Etilde, Gamma), and its stresses
    ``sigma = S + T^T``, ``s = S + T + T^T`` give ``T = s - sigma``, ``psi_E = sigma - T^T``.
    """
    eye = np.eye(np.shape(E)[-1])
    sigma, s, m = micromorphic_stresses(E, eye + Etilde - _T(E), Gamma, material)
    T = s - sigma
    psi_E = sigma - _T(T)
    return 0.5 * (psi_E + _T(psi_E)), T, m   # symmetric to the last bit


def micromorphic_finite_energy(grad_u, chi, grad_chi, material: MicromorphicMaterial):
    """Stored energy per unit reference volume psi [J/m^3] (arguments as
    :func:`finite_strain_measures`)."""
    _, E, Et, G = finite_strain_measures(grad_u, chi, grad_chi)
    eye = np.eye(E.shape[-1])
    return micromorphic_energy(E, eye + Et - _T(E), G, material)


def micromorphic_finite_stresses(grad_u, chi, grad_chi, material: MicromorphicMaterial):
    """Reference-configuration stresses of the finite-strain micromorphic law (no mesh).

    Args:
        grad_u: ``grad_u[..., i, J] = u_i,J``, the reference displacement gradient
            (``F = I + grad_u``), shape (..., d, d), d = 2 (plane strain) or 3.
        chi: the micro-deformation ``chi = I + phi``, shape (..., d, d).
        grad_chi: ``grad_chi[..., i, J, K] = chi_iJ,K`` (reference gradient), shape
            (..., d, d, d).
        material: the 18 moduli.

    Returns:
        ``(S, Sigma, M)``: the second Piola-Kirchhoff stress ``S[..., I, J]``
        (``S = F^-1 dpsi/dF``, second index the face: nominal traction ``F S N``), the
        symmetric reference micro-stress ``Sigma[..., I, J]`` and the reference
        higher-order stress ``M[..., I, J, K] = dpsi/dGamma_IJK`` (last index the
        gradient direction / face), as in the module docstring. Tardigrade's order:
        :func:`to_tardigrade_order`.
    """
    F, E, Et, G = finite_strain_measures(grad_u, chi, grad_chi)
    eye = np.eye(E.shape[-1])
    psi_E, T, H = energy_partials(E, Et, G, material)
    Ci = np.linalg.inv(_T(F) @ F)
    CiPsi = Ci @ (eye + Et)
    CiGamma = np.einsum("...IS,...SQR->...IQR", Ci, G)
    extra = CiPsi @ _T(T) + np.einsum("...IQR,...JQR->...IJ", CiGamma, H)
    S = psi_E + extra
    Sigma = psi_E + (extra + _T(extra))   # symmetric to the last bit
    return S, Sigma, H


def micromorphic_finite_nominal_stresses(grad_u, chi, grad_chi, material: MicromorphicMaterial):
    """``(P, Q, R)``: ``P[i, J] = dpsi/dF_iJ``, ``Q[i, J] = dpsi/dchi_iJ``,
    ``R[i, J, K] = dpsi/dchi_iJ,K`` (the integrands of the residual): ``P = F S``,
    ``Q = F T``, ``R_iJK = F_iI M_IJK``."""
    F, E, Et, G = finite_strain_measures(grad_u, chi, grad_chi)
    _, T, H = energy_partials(E, Et, G, material)
    S, _, _ = micromorphic_finite_stresses(grad_u, chi, grad_chi, material)
    return F @ S, F @ T, np.einsum("...iI,...IJK->...iJK", F, H)


def push_forward(grad_u, chi, S, Sigma, M):
    """Current-configuration stresses ``(sigma, s, m)`` of the reference ones:
    ``sigma = F S F^T / J`` (traction ``sigma_ij n_j``), ``s = F Sigma F^T / J``,
    ``m_ijk = F_iI chi_jJ F_kK M_IJK / J`` (double traction ``m_ijk n_k``)."""
    F = np.eye(np.shape(grad_u)[-1]) + np.asarray(grad_u, dtype=float)
    J = np.linalg.det(F)[..., None, None]
    chi = np.asarray(chi, dtype=float)
    m = np.einsum("...iI,...jJ,...kK,...IJK->...ijk", F, chi, F, M) / J[..., None]
    return F @ S @ _T(F) / J, F @ Sigma @ _T(F) / J, m


def to_tardigrade_order(S, Sigma, M):
    """``(PK2, Sigma, M_T)`` in the index order of Tardigrade's
    ``linearElasticityReference``: ``PK2 = S^T``, ``M_T[I, J, K] = M[J, K, I]``."""
    return _T(S), Sigma, np.einsum("...JKI->...IJK", M)


# ---- UFL --------------------------------------------------------------------------------

def ufl_measures(F, chi, grad_chi):
    """``(E, Etilde, Gamma)`` of UFL ``F``, ``chi`` and ``grad_chi`` (any dimension)."""
    d = ufl.shape(F)[0]
    eye = ufl.Identity(d)
    i, I_, J_, K_ = ufl.indices(4)
    E = (F.T * F - eye) / 2
    Etilde = F.T * chi - eye
    Gamma = ufl.as_tensor(F[i, I_] * grad_chi[i, J_, K_], (I_, J_, K_))
    return E, Etilde, Gamma


def _kinematics(u, phi):
    d = ufl.shape(u)[0]
    phi = as_tensor_field(phi, d)
    eye = ufl.Identity(d)
    return eye + ufl.grad(u), eye + phi, ufl.grad(phi)


def energy_density(u, phi, c):
    """Stored energy per unit reference volume psi of the fields (UFL)."""
    return strain_energy_density(*ufl_measures(*_kinematics(u, phi)), c)


def nominal_stresses(u, phi, c):
    """``(P, Q, R) = (dpsi/dF, dpsi/dchi, dpsi/d grad chi)`` (UFL, by ``ufl.diff``)."""
    F0, chi0, G0 = _kinematics(u, phi)
    F, chi, G = ufl.variable(F0), ufl.variable(chi0), ufl.variable(G0)
    psi = strain_energy_density(*ufl_measures(F, chi, G), c)
    return ufl.diff(psi, F), ufl.diff(psi, chi), ufl.diff(psi, G)


def ufl_stresses(u, phi, c):
    """``(S, Sigma, M)`` of the fields (UFL): the formulas of the module docstring with
    ``psi_E``, ``T``, ``H`` by ``ufl.diff`` of psi in (E, Etilde, Gamma)."""
    F, chi, G0 = _kinematics(u, phi)
    E0, Et0, Gam0 = ufl_measures(F, chi, G0)
    E, Et, Gam = ufl.variable(E0), ufl.variable(Et0), ufl.variable(Gam0)
    psi = strain_energy_density(E, Et, Gam, c)
    psi_E = ufl.sym(ufl.diff(psi, E))   # E is symmetric: its conjugate is the symmetric part
    T, H = ufl.diff(psi, Et), ufl.diff(psi, Gam)
    Ci = ufl.inv(F.T * F)
    I_, J_, K_, Q_, R_, S_ = ufl.indices(6)
    extra = (Ci * (F.T * chi) * T.T
             + ufl.as_tensor(Ci[I_, S_] * Gam0[S_, Q_, R_] * H[J_, Q_, R_], (I_, J_)))
    return psi_E + extra, psi_E + extra + extra.T, H


class MicromorphicFiniteStrain(ContinuumModel):
    """Finite-strain isotropic micromorphic elasticity (reference configuration) with a
    :class:`~granfe.models.micromorphic.MicromorphicMaterial`; fields ``u`` and
    ``phi = chi - I`` as :class:`~granfe.models.micromorphic.Micromorphic`."""

    name = "micromorphic_finite_strain"
    linear = False
    material_type = MicromorphicMaterial
    #: C compiler flags this model's forms want: gcc needs ~13 min (-O2, dolfinx's default),
    #: ~100 s (-O1) or ~30 s (-O0) for the 3D Jacobian on a loaded 2-core machine
    #: (ContinuumProblem, the steppers and the writer compile with it).
    jit_options: ClassVar[dict] = {"cffi_extra_compile_args": ["-O0", "-g0"]}

    # the same fields, constants, inertia (reference density rho, micro-inertia rho i)
    # and infinitesimal rigid modes as the small-strain model
    fields = staticmethod(Micromorphic.fields)
    rigid_modes = staticmethod(Micromorphic.rigid_modes)
    constant_values = Micromorphic.constant_values
    _split = Micromorphic._split
    inertia_work = Micromorphic.inertia_work
    kinetic_energy = Micromorphic.kinetic_energy

    def internal_work(self, w, dw, state):
        """The first variation of psi: ``P : grad du + Q : dphi + R : grad dphi``."""
        u, phi = self._split(w)
        du, dphi = self._split(dw)
        P, Q, R = nominal_stresses(u, phi, self.constants)
        return ufl.inner(P, ufl.grad(du)) + ufl.inner(Q, dphi) + ufl.inner(R, ufl.grad(dphi))

    def stored_energy(self, w, state):
        return energy_density(*self._split(w), self.constants)

    def stresses(self, w, state):
        """Reference stresses (PK2 ``S``, ``Sigma``, ``M``) and the Cauchy stress
        ``sigma = F S F^T / J``."""
        u, phi = self._split(w)
        S, Sigma, M = ufl_stresses(u, phi, self.constants)
        F = ufl.Identity(ufl.shape(u)[0]) + ufl.grad(u)
        return {"pk2": S, "micro_stress": Sigma, "higher_order_stress": M,
                "cauchy": F * S * F.T / ufl.det(F)}

    def plot_fields(self, w, state):
        u, phi = self._split(w)
        out = plot_fields(u, phi, self.stresses(w, state)["cauchy"], self.gdim)
        out["J"] = ufl.det(ufl.Identity(self.gdim) + ufl.grad(u))
        return out
