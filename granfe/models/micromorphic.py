"""Small-strain isotropic micromorphic (Eringen-Mindlin) elasticity, seed 002 §1.1.

Fields: displacement ``u`` and micro-displacement ``phi = chi - I``, the departure of the
micro-deformation ``chi`` from the identity (2D plane strain: the 4 in-plane components,
3D: 9). The unknown is ``phi`` rather than ``chi`` so that zero is the undeformed state (the
default of every initial condition and boundary value here); Tardigrade's dofs are the same.

Deformation measures: the linearisations of Regueiro's (2010) ``E = (F^T F - I)/2``,
``Psi - I = F^T chi - I`` and ``Gamma_KLM = F_kK chi_kL,M`` used by the open Tardigrade
``micromorphic_linear_elasticity``, so its constants carry over one to one::

    eps_ij = (u_i,j + u_j,i) / 2            macro strain
    E_ij   = u_j,i + phi_ij                 micro strain (relative deformation)
    G_ijk  = phi_ij,k                       micro-deformation gradient

``E`` vanishes for a rigid rotation (``phi = grad u`` skew) and for ``chi = F^-T``.
Equivalently ``E = 2 eps - gamma`` with Eringen's relative deformation
``gamma = grad u - phi`` (the conjugate of sigma below): the same model family, in the
constants of Tardigrade rather than of a (eps, gamma) energy. The
energy is ``W = eps:A:eps/2 + E:B:E/2 + G:C:G/2 + eps:D:E`` with Eringen's isotropic
tensors (Eringen 1999, Microcontinuum Field Theories I; as Tardigrade's
``formIsotropicA..D``, whose unit-test values the tests reproduce)::

    A_KLMN = lam d_KL d_MN + mu (d_KM d_LN + d_KN d_LM)
    B_KLMN = (eta - tau) d_KL d_MN + kappa d_KM d_LN + nu d_KN d_LM
             - sigma (d_KM d_LN + d_KN d_LM)
    D_KLMN = tau d_KL d_MN + sigma (d_KM d_LN + d_KN d_LM)
    C_KLMNPQ = tau1 (d_KL d_MN d_PQ + d_KQ d_LM d_NP) + tau2 (d_KL d_MP d_NQ + d_KM d_LQ d_NP)
             + tau3 d_KL d_MQ d_NP + tau4 d_KN d_LM d_PQ + tau5 (d_KM d_LN d_PQ + d_KP d_LM d_NQ)
             + tau6 d_KM d_LP d_NQ + tau7 d_KN d_LP d_MQ + tau8 (d_KP d_LQ d_MN + d_KQ d_LN d_MP)
             + tau9 d_KN d_LQ d_MP + tau10 d_KP d_LN d_MQ + tau11 d_KQ d_LP d_MN

Stresses and index conventions (the virtual work density is
``sigma_ij du_i,j + (s_ij - sigma_ij) dphi_ij + m_ijk dphi_ij,k``, i.e. Eringen's
``sigma : (grad du - dphi) + s : dphi + m : grad dphi``):

* ``sigma`` [Pa], unsymmetric Cauchy-like stress, conjugate to ``u_i,j``: traction
  ``t_i = sigma_ij n_j`` (the second index names the face), balance ``sigma_ij,j + f_i = 0``;
* ``s`` [Pa], symmetric micro-stress;
* ``m`` [Pa m], higher-order (double) stress, conjugate to ``phi_ij,k``: the surface double
  traction is ``m_ijk n_k`` (the last index names the face), balance of the first moment
  of momentum ``m_ijk,k + sigma_ij - s_ij + l_ij = 0`` with the body double force ``l``.

With ``S = dW/d eps`` and ``T = dW/dE``: ``sigma = S + T^T``, ``s = S + T + T^T``.
In plane strain all out-of-plane components of u, phi and their gradients vanish and the
same contractions run over two indices.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import dolfinx_solver  # noqa: F401

import numpy as np
import ufl

from granfe.models.base import ContinuumModel, Field

__all__ = [
    "Micromorphic",
    "MicromorphicMaterial",
    "micromorphic_stresses",
    "micromorphic_energy",
    "smith_T",
    "strains",
    "strain_energy_density",
    "stresses",
]

_TAUS = tuple(f"tau{i}" for i in range(1, 12))
_MODULI = ("lam", "mu", "eta", "tau", "kappa", "nu", "sigma") + _TAUS


# ---- material ---------------------------------------------------------------------------

def smith_T(taus) -> np.ndarray:
    """Smith's (1968) 3x3 matrix of the vector (trace) part of C (Tardigrade's
    ``construct_T_matrix``): C is positive definite on the trace parts iff T has positive
    eigenvalues (it is similar to a symmetric matrix, so they are real)."""
    t1, t2, t3, t4, t5, t6, t7, t8, t9, t10, t11 = taus
    return np.array([
        [t1 + t2 + 3 * t3 + t7 + t10, 3 * t1 + t4 + t5 + t8 + t11, 3 * t2 + t5 + t6 + t8 + t9],
        [3 * t1 + t2 + t3 + t8 + t11, t1 + 3 * t4 + t5 + t7 + t9, t2 + 3 * t5 + t6 + t8 + t10],
        [t1 + 3 * t2 + t3 + t8 + t9, t1 + t4 + 3 * t5 + t8 + t10, t2 + t5 + 3 * t6 + t7 + t11],
    ])


@dataclass(frozen=True)
class MicromorphicMaterial:
    """Isotropic small-strain micromorphic solid (18 moduli in Eringen's notation).

    Attributes:
        lam, mu: macro-strain moduli (A) [Pa].
        eta, tau, kappa, nu, sigma: micro-strain (B) and coupling (D: tau, sigma) moduli [Pa].
        tau1 ... tau11: moduli of the micro-deformation gradient (C) [Pa m^2] (= N).
        rho: mass density [kg/m^3].
        micro_inertia: isotropic micro-inertia per unit mass ``i`` [m^2], the kinetic energy
            density being ``rho |du/dt|^2 / 2 + rho i |dphi/dt|^2 / 2`` (a micropolar
            solid with rotation inertia ``rho j`` has ``j = 2 i``).
        allow_indefinite: skip the positive-definiteness check (constitutive tests only).

    Construction checks that W is positive definite in 3D (Smith 1968, as in Tardigrade's
    ``linear_elastic_parameter_constraint_equations`` less its g8, which restates the
    deviatoric determinant inconsistently; the tests hold the set against the eigenvalues
    of the assembled tensors; :meth:`conditions` lists them):
    on the deviatoric strains ``mu > 0``, ``kappa + nu - 2 sigma > 0``,
    ``mu (kappa + nu - 2 sigma) - 2 sigma^2 > 0``; on the volumetric ones
    ``3 lam + 2 mu > 0``, ``kappa + nu + 3 eta - 3 tau - 2 sigma > 0`` and its determinant;
    on the skew micro strain ``kappa - nu > 0``; and on the SO(3)-irreducible parts of G:
    fully symmetric ``tau7 + 2 tau8 + tau9 + tau10 + tau11 > 0``, totally skew
    ``tau7 + 2 tau8 - tau9 - tau10 - tau11 > 0``, mixed ``tau7 - tau8 -
    sqrt(((tau9-tau10)^2 + (tau10-tau11)^2 + (tau11-tau9)^2)/2) > 0``, and the traces
    (Smith's T matrix: trace, second invariant and determinant > 0). Positive
    definiteness in 3D implies it in plane strain.
    """

    lam: float
    mu: float
    eta: float
    tau: float
    kappa: float
    nu: float
    sigma: float
    tau1: float
    tau2: float
    tau3: float
    tau4: float
    tau5: float
    tau6: float
    tau7: float
    tau8: float
    tau9: float
    tau10: float
    tau11: float
    rho: float = 1.0
    micro_inertia: float = 1.0
    allow_indefinite: bool = False

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "allow_indefinite":
                if not isinstance(value, bool):
                    raise ValueError(f"MicromorphicMaterial.allow_indefinite must be a bool, got {value!r}")
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"MicromorphicMaterial.{f.name} must be a finite number, got {value!r}")
        for name in ("rho", "micro_inertia"):
            if getattr(self, name) <= 0.0:
                raise ValueError(f"MicromorphicMaterial.{name} = {getattr(self, name)!r} violates {name} > 0")
        if self.allow_indefinite:
            return
        for rule, value in self.conditions():
            if not value > 0.0:
                raise ValueError(
                    f"MicromorphicMaterial violates {rule} (value {value:.6g}): the micromorphic "
                    f"energy is not positive definite (Smith 1968); pass allow_indefinite=True "
                    f"to accept it for constitutive testing"
                )

    @property
    def taus(self) -> tuple[float, ...]:
        return tuple(getattr(self, t) for t in _TAUS)

    def moduli(self) -> dict[str, float]:
        """The 18 moduli by name."""
        return {k: float(getattr(self, k)) for k in _MODULI}

    def conditions(self) -> list[tuple[str, float]]:
        """Smith's positive-definiteness conditions as (rule, value); each value must be > 0."""
        lam, mu, eta, tau, kappa, nu, sigma = (self.lam, self.mu, self.eta, self.tau, self.kappa,
                                               self.nu, self.sigma)
        t = self.taus
        t7, t8, t9, t10, t11 = t[6:]
        k2 = kappa + nu - 2 * sigma
        k3 = kappa + nu + 3 * eta - 3 * tau - 2 * sigma
        T = smith_T(t)
        mixed = math.sqrt(((t9 - t10) ** 2 + (t10 - t11) ** 2 + (t11 - t9) ** 2) / 2)
        return [
            ("mu > 0", mu),
            ("kappa + nu - 2 sigma > 0", k2),
            ("mu (kappa + nu - 2 sigma) - 2 sigma^2 > 0", mu * k2 - 2 * sigma**2),
            ("3 lam + 2 mu > 0", 3 * lam + 2 * mu),
            ("kappa + nu + 3 eta - 3 tau - 2 sigma > 0", k3),
            ("(kappa + nu + 3 eta - 3 tau - 2 sigma)(3 lam + 2 mu) - (3 tau + 2 sigma)^2 > 0",
             k3 * (3 * lam + 2 * mu) - (3 * tau + 2 * sigma) ** 2),
            ("kappa - nu > 0", kappa - nu),
            ("tau7 + 2 tau8 + tau9 + tau10 + tau11 > 0 (fully symmetric part of grad chi)",
             t7 + 2 * t8 + t9 + t10 + t11),
            ("tau7 + 2 tau8 - tau9 - tau10 - tau11 > 0 (totally skew part of grad chi)",
             t7 + 2 * t8 - t9 - t10 - t11),
            ("tau7 - tau8 - sqrt(((tau9 - tau10)^2 + (tau10 - tau11)^2 + (tau11 - tau9)^2) / 2)"
             " > 0 (mixed-symmetry part of grad chi)", t7 - t8 - mixed),
            ("trace of Smith's T(tau1..tau11) > 0 (trace parts of grad chi)", float(np.trace(T))),
            ("second invariant of Smith's T(tau1..tau11) > 0 (trace parts of grad chi)",
             float((np.trace(T) ** 2 - np.trace(T @ T)) / 2)),
            ("det of Smith's T(tau1..tau11) > 0 (trace parts of grad chi)", float(np.linalg.det(T))),
        ]

    @classmethod
    def micropolar_limit(cls, lam, mu, kappa, gamma, *, penalty, rho=1.0, j=1.0, **kwargs):
        """A micromorphic material that tends to the micropolar one
        (:class:`~granfe.materials.MicropolarMaterial` ``lam, mu, kappa, gamma`` with
        ``alpha = beta = 0``) as ``penalty`` [Pa] grows.

        ``penalty |sym phi|^2 / 2`` is added to W through ``mu += penalty / 2``,
        ``sigma = -penalty / 2`` (so phi tends to a rotation ``phi = -e . phi_p``), and the
        other moduli make W of a skew phi the micropolar energy. In general that energy has
        ``lam_p = lam + eta + tau``, ``2 mu_p + kappa_p = 2 mu + kappa + nu + 2 sigma``,
        ``kappa_p = kappa - nu``, ``alpha_p = 2 tau8 - tau9 - tau11``,
        ``beta_p = -(tau4 - 2 tau5 + tau6)``, ``gamma_p = tau4 - 2 tau5 + tau6 + 2 tau7
        - 2 tau8 + tau9 - 2 tau10 + tau11`` (2D: gamma_p only); here ``eta = tau = nu = 0``,
        ``tau7 = gamma_p / 2`` and the other taus vanish. ``j`` is the micropolar rotary
        inertia per unit mass: ``micro_inertia = j / 2``."""
        return cls(lam=lam, mu=mu + penalty / 2, eta=0.0, tau=0.0, kappa=kappa, nu=0.0,
                   sigma=-penalty / 2, tau1=0.0, tau2=0.0, tau3=0.0, tau4=0.0, tau5=0.0, tau6=0.0,
                   tau7=gamma / 2, tau8=0.0, tau9=0.0, tau10=0.0, tau11=0.0, rho=rho,
                   micro_inertia=j / 2, **kwargs)


# ---- the material-point law (numpy) ------------------------------------------------------

def _np_measures(grad_u, chi, grad_chi):
    grad_u = np.asarray(grad_u, dtype=float)
    d = grad_u.shape[-1]
    phi = np.asarray(chi, dtype=float) - np.eye(d)
    eps = 0.5 * (grad_u + np.swapaxes(grad_u, -1, -2))
    E = np.swapaxes(grad_u, -1, -2) + phi
    return eps, E, np.asarray(grad_chi, dtype=float), d


def _np_traces(G):
    a = np.einsum("...kkm->...m", G)   # a_M = G_KKM
    b = np.einsum("...kll->...k", G)   # b_K = G_KLL
    c = np.einsum("...klk->...l", G)   # c_L = G_KLK
    return a, b, c


def micromorphic_stresses(grad_u, chi, grad_chi, material: MicromorphicMaterial):
    """Stresses of the small-strain micromorphic law at material points (no mesh).

    Args:
        grad_u: ``grad_u[..., i, j] = u_i,j``, shape (..., d, d), d = 2 (plane strain) or 3.
        chi: the micro-deformation ``chi = I + phi``, shape (..., d, d).
        grad_chi: ``grad_chi[..., i, j, k] = chi_ij,k``, shape (..., d, d, d).
        material: the moduli.

    Returns:
        ``(sigma, s, m)``: the unsymmetric Cauchy-like stress ``sigma[..., i, j]``
        (``t_i = sigma_ij n_j``), the symmetric micro-stress ``s[..., i, j]`` and the
        higher-order stress ``m[..., i, j, k]`` (double traction ``m_ijk n_k``), in the
        conventions of the module docstring. Same law as the UFL :func:`stresses`.
    """
    c = material
    eps, E, G, d = _np_measures(grad_u, chi, grad_chi)
    eye = np.eye(d)
    tr_e = np.einsum("...ii->...", eps)[..., None, None]
    tr_E = np.einsum("...ii->...", E)[..., None, None]
    ET = np.swapaxes(E, -1, -2)
    S = (c.lam * tr_e * eye + 2 * c.mu * eps + c.tau * tr_E * eye + c.sigma * (E + ET))
    T = ((c.eta - c.tau) * tr_E * eye + c.kappa * E + c.nu * ET - c.sigma * (E + ET)
         + c.tau * tr_e * eye + 2 * c.sigma * eps)
    TT = np.swapaxes(T, -1, -2)
    sigma = S + TT
    s = S + T + TT
    m = _np_higher_order(G, c.taus, eye)
    return sigma, s, m


def _np_higher_order(G, taus, eye):
    t1, t2, t3, t4, t5, t6, t7, t8, t9, t10, t11 = taus
    a, b, c = _np_traces(G)

    def outer(delta_pair, vec):
        # delta_pair in {"KL", "LM", "KM"}: d_XY v_Z over (K, L, M)
        if delta_pair == "KL":
            return np.einsum("kl,...m->...klm", eye, vec)
        if delta_pair == "LM":
            return np.einsum("lm,...k->...klm", eye, vec)
        return np.einsum("km,...l->...klm", eye, vec)

    def perm(p):
        return np.einsum(f"...{p}->...klm", G)

    return (t1 * (outer("KL", b) + outer("LM", a)) + t2 * (outer("KL", c) + outer("KM", a))
            + t3 * outer("KL", a) + t4 * outer("LM", b) + t5 * (outer("LM", c) + outer("KM", b))
            + t6 * outer("KM", c) + t7 * G + t8 * (perm("lmk") + perm("mkl"))
            + t9 * perm("kml") + t10 * perm("lkm") + t11 * perm("mlk"))


def micromorphic_energy(grad_u, chi, grad_chi, material: MicromorphicMaterial):
    """Stored energy density W [J/m^3] at material points (arguments as
    :func:`micromorphic_stresses`)."""
    c = material
    eps, E, G, d = _np_measures(grad_u, chi, grad_chi)
    tr_e, tr_E = np.einsum("...ii->...", eps), np.einsum("...ii->...", E)
    EE = np.einsum("...ij,...ij->...", E, E)
    EET = np.einsum("...ij,...ji->...", E, E)
    W = (c.lam / 2 * tr_e**2 + c.mu * np.einsum("...ij,...ij->...", eps, eps)
         + (c.eta - c.tau) / 2 * tr_E**2 + (c.kappa - c.sigma) / 2 * EE + (c.nu - c.sigma) / 2 * EET
         + c.tau * tr_e * tr_E + 2 * c.sigma * np.einsum("...ij,...ij->...", eps, E))
    m = _np_higher_order(G, c.taus, np.eye(d))
    return W + 0.5 * np.einsum("...klm,...klm->...", m, G)


# ---- UFL --------------------------------------------------------------------------------

def as_tensor_field(phi, gdim: int):
    """The micro-displacement as a (gdim, gdim) UFL matrix, also from a flat vector (a
    generalized-alpha mid-point combination is split into flat components)."""
    if len(ufl.shape(phi)) == 2:
        return phi
    return ufl.as_matrix([[phi[gdim * i + j] for j in range(gdim)] for i in range(gdim)])


def strains(u, phi):
    """``(eps, E, G)``: macro strain, micro strain ``E_ij = u_j,i + phi_ij`` and
    ``G_ijk = phi_ij,k`` (UFL)."""
    gdim = ufl.shape(u)[0]
    phi = as_tensor_field(phi, gdim)
    return ufl.sym(ufl.grad(u)), ufl.grad(u).T + phi, ufl.grad(phi)


def _higher_order_energy2(G, c):
    """``G:C:G`` (twice the C energy) by contractions: traces a, b, c and index permutations."""
    i, j, k = ufl.indices(3)
    a = ufl.as_vector(G[i, i, k], k)
    b = ufl.as_vector(G[k, i, i], k)
    cc = ufl.as_vector(G[i, k, i], k)
    return (2 * c.tau1 * ufl.dot(a, b) + 2 * c.tau2 * ufl.dot(a, cc) + c.tau3 * ufl.dot(a, a)
            + c.tau4 * ufl.dot(b, b) + 2 * c.tau5 * ufl.dot(b, cc) + c.tau6 * ufl.dot(cc, cc)
            + c.tau7 * G[i, j, k] * G[i, j, k] + 2 * c.tau8 * G[i, j, k] * G[k, i, j]
            + c.tau9 * G[i, j, k] * G[i, k, j] + c.tau10 * G[i, j, k] * G[j, i, k]
            + c.tau11 * G[i, j, k] * G[k, j, i])


def strain_energy_density(eps, E, G, c):
    """``W = eps:A:eps/2 + E:B:E/2 + G:C:G/2 + eps:D:E`` with the constants ``c``."""
    tr_e, tr_E = ufl.tr(eps), ufl.tr(E)
    W = (c.lam / 2 * tr_e**2 + c.mu * ufl.inner(eps, eps)
         + (c.eta - c.tau) / 2 * tr_E**2 + (c.kappa - c.sigma) / 2 * ufl.inner(E, E)
         + (c.nu - c.sigma) / 2 * ufl.inner(E, E.T)
         + c.tau * tr_e * tr_E + 2 * c.sigma * ufl.inner(eps, E))
    return W + _higher_order_energy2(G, c) / 2


def stresses(u, phi, c):
    """``(sigma, s, m)`` of the fields (UFL), by ``ufl.diff`` of the energy: with
    ``S = dW/d eps``, ``T = dW/dE``, ``sigma = S + T^T``, ``s = S + T + T^T``, ``m = dW/dG``."""
    eps0, E0, G0 = strains(u, phi)
    eps, E, G = ufl.variable(eps0), ufl.variable(E0), ufl.variable(G0)
    W = strain_energy_density(eps, E, G, c)
    S, T, m = ufl.diff(W, eps), ufl.diff(W, E), ufl.diff(W, G)
    S = ufl.sym(S)   # eps is symmetric: its conjugate is the symmetric part
    return S + T.T, S + T + T.T, m


def plot_fields(u, phi, sigma, gdim: int) -> dict:
    """Scalar fields to render of a micromorphic state: magnitudes of u and phi, the von Mises
    stress of sym(sigma), and every component of u, phi and sigma."""
    s = ufl.sym(sigma)
    dev = s - ufl.tr(s) / gdim * ufl.Identity(gdim)
    out = {"u_magnitude": ufl.sqrt(ufl.inner(u, u)),
           "von_mises": ufl.sqrt(1.5 * ufl.inner(dev, dev)),
           "phi_magnitude": ufl.sqrt(ufl.inner(phi, phi))}
    axes = "xyz"
    for i in range(gdim):
        out[f"u_{axes[i]}"] = u[i]
        for j in range(gdim):
            out[f"phi_{axes[i]}{axes[j]}"] = phi[i, j]
            out[f"sigma_{axes[i]}{axes[j]}"] = sigma[i, j]
    return out


class Micromorphic(ContinuumModel):
    """Small-strain isotropic micromorphic elasticity with a :class:`MicromorphicMaterial`."""

    name = "micromorphic"
    linear = True
    material_type = MicromorphicMaterial

    @staticmethod
    def fields(gdim):
        axes = "xyz"[:gdim]
        return (Field("u", (gdim,), tuple(f"u_{a}" for a in axes), 2),
                Field("phi", (gdim, gdim), tuple(f"phi_{a}{b}" for a in axes for b in axes), 1))

    def constant_values(self, material):
        return {**material.moduli(), "rho": material.rho,
                "rho_i": material.rho * material.micro_inertia}

    def _split(self, w):
        u, phi = w
        return u, as_tensor_field(phi, ufl.shape(u)[0])

    def internal_work(self, w, dw, state):
        u, phi = self._split(w)
        du, dphi = self._split(dw)
        sigma, s, m = stresses(u, phi, self.constants)
        return (ufl.inner(sigma, ufl.grad(du)) + ufl.inner(s - sigma, dphi)
                + ufl.inner(m, ufl.grad(dphi)))

    def inertia_work(self, a, dw):
        au, aphi = self._split(a)
        du, dphi = self._split(dw)
        return self.constants.rho * ufl.inner(au, du) + self.constants.rho_i * ufl.inner(aphi, dphi)

    def kinetic_energy(self, v):
        vu, vphi = self._split(v)
        c = self.constants
        return c.rho / 2 * ufl.inner(vu, vu) + c.rho_i / 2 * ufl.inner(vphi, vphi)

    def stored_energy(self, w, state):
        return strain_energy_density(*strains(*self._split(w)), self.constants)

    def stresses(self, w, state):
        sigma, s, m = stresses(*self._split(w), self.constants)
        return {"sigma": sigma, "micro_stress": s, "higher_order_stress": m}

    @staticmethod
    def rigid_modes(gdim):
        """Translations (u = e_k, phi = 0) and rotations (u = W x, phi = W, W skew): both
        strains and G vanish."""
        def translation(k):
            return lambda x: np.vstack([np.full(x.shape[1], float(i == k)) for i in range(gdim)])

        modes = [(translation(k), None) for k in range(gdim)]
        axes = [np.array([[0.0, -1.0], [1.0, 0.0]])] if gdim == 2 else [
            np.cross(np.eye(3)[k], -np.eye(3)) for k in range(3)]   # W v = e_k x v
        for W in axes:
            modes.append((lambda x, W=W: W @ x[:gdim],
                           lambda x, W=W: np.tile(W.reshape(-1, 1), x.shape[1])))
        return modes

    def plot_fields(self, w, state):
        u, phi = self._split(w)
        return plot_fields(u, phi, self.stresses(w, state)["sigma"], self.gdim)
