"""Small-strain micromorphic Drucker-Prager elastoplasticity on three levels (after Regueiro
2009, 2010).

Fields, measures and stresses are those of :mod:`granfe.models.micromorphic` (``u``,
``phi = chi - I``; ``eps = sym grad u``, ``E = grad u^T + phi``, ``G = grad phi``). As in
Regueiro's model each level has its own plastic deformation and its own pressure-sensitive
yield function, plastic potential and hardening. Here, in small strain, the plastic parts
are additive on the three measures::

    eps = eps_e + eps_p,     E = E_e + E_p,     G_klM = G_e_klM + G_p_klM,

and the yield stresses are the conjugates of the measures in the energy
``W(eps_e, E_e, G_e)``:

* macro level: ``S = dW/d eps`` (symmetric); ``S = sym sigma`` where the relative stress
  vanishes (a homogeneous state without a body double force);
* micro level: the symmetric part of the relative stress ``T = dW/dE = s - sigma`` (the
  micro-stress relative to the macro one, Regueiro's ``Sigma - S``); its skew part stays
  elastic, as the skew force stress of the micropolar Drucker-Prager model;
* higher-order level: one cone per slice ``m_klM`` of the double stress (the last index
  names the face), with ``p_M = m_kkM / 3`` and ``dev m_klM = m_klM - p_M d_kl``: Regueiro's
  (2010) ``F_M^{grad chi}``, one yield function per M.

On every level (stress ``t``: 3 x 3, tension positive, ``p = tr t / 3``)::

    f = sqrt(J2) + A p - (k0 + H e_q),    g = sqrt(J2) + B p,    J2 = 1/2 dev t : dev t,

with ``(A, B, k0)`` from a Mohr-Coulomb cohesion, friction and dilatancy angle through
:func:`~granfe.models.drucker_prager.drucker_prager_constants` (non-associated when the
dilatancy angle is below the friction angle), linear hardening ``H >= 0`` and the return to
the apex where the radial return would cross it.

Decoupled levels, closed-form returns: with ``D = 0`` (``tau = sigma = 0``) and ``C = tau7``
times the identity (the other ten taus zero) the energy splits into the three levels, each
isotropic in its own measure (macro ``G = mu, K = lam + 2 mu / 3``; micro ``G = (kappa + nu)
/ 2, K = eta + (kappa + nu) / 3``; each higher-order slice ``G = tau7 / 2, K = tau7 / 3``), so
every return is the radial one of classical Drucker-Prager, closed form in UFL, and SNES
gets the consistent tangent from ``ufl.derivative``. The model checks those moduli; a
coupled set (D or the other taus) needs an iterative return over all levels at once:
:mod:`granfe.models.micromorphic_iterative` (the same material, the return at the points).
Plane strain keeps the out-of-plane components of the plastic parts (3 x 3).

Quadrature-point state: ``plastic_strain`` (3 x 3), ``plastic_micro_strain`` (3 x 3,
symmetric), ``plastic_micro_gradient`` (gdim x 3 x 3, ``[M, k, l] = G_p_klM``),
``equivalent_plastic_strain`` (2 + gdim: macro, micro, one per slice M) and ``yielding``
(3: a level yielded in the last committed step, the higher-order one in any slice).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import dolfinx_solver  # noqa: F401

import ufl

from granfe.models.drucker_prager import MATCHES, drucker_prager_constants
from granfe.models.micromorphic import Micromorphic, MicromorphicMaterial, strains

__all__ = ["Cone", "MicromorphicDruckerPrager", "MicromorphicDruckerPragerMaterial", "cone_return"]

LEVELS = ("macro", "micro", "gradient")
_ZERO_TAUS = ("tau1", "tau2", "tau3", "tau4", "tau5", "tau6", "tau8", "tau9", "tau10", "tau11")


@dataclass(frozen=True)
class Cone:
    """A Drucker-Prager cone of one level, matched to Mohr-Coulomb.

    Attributes:
        cohesion: c (>= 0) [Pa] on the macro and micro levels, [Pa m] on the higher-order one.
        friction_deg: phi [deg] in [0, 90).
        dilatancy_deg: psi [deg] in [0, phi] (non-associated below phi).
        hardening: H >= 0 [Pa] per unit equivalent plastic strain (Pa m^2 on the
            higher-order level, whose plastic strain is a gradient [1/m]).
        match: ``"triaxial_compression"`` (the Mohr-Coulomb compression meridian) or
            ``"plane_strain"``, see :func:`~granfe.models.drucker_prager.drucker_prager_constants`.
    """

    cohesion: float
    friction_deg: float
    dilatancy_deg: float = 0.0
    hardening: float = 0.0
    match: str = "triaxial_compression"

    def __post_init__(self):
        checks = (("cohesion", self.cohesion >= 0, ">= 0"),
                  ("friction_deg", 0 <= self.friction_deg < 90, "in [0, 90) degrees"),
                  ("dilatancy_deg", 0 <= self.dilatancy_deg <= self.friction_deg,
                   "in [0, friction_deg] degrees"),
                  ("hardening", self.hardening >= 0, ">= 0 (no softening here)"))
        for name, ok, rule in checks:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not math.isfinite(value) or not ok:
                raise ValueError(f"Cone.{name} must be {rule}, got {value!r}")
        if self.match not in MATCHES:
            raise ValueError(f"Cone.match must be one of {MATCHES}, got {self.match!r}")
        if self.cohesion == 0 and self.friction_deg == 0:
            raise ValueError("Cone: cohesion 0 with friction 0 has no strength")

    @property
    def constants(self) -> tuple[float, float, float]:
        """``(A, B, k0)`` of ``f = sqrt(J2) + A p - k0``."""
        return drucker_prager_constants(self.friction_deg, self.dilatancy_deg, self.cohesion,
                                        self.match)


@dataclass(frozen=True)
class MicromorphicDruckerPragerMaterial:
    """Micromorphic elasticity with a Drucker-Prager cone on each level (None: elastic).

    Attributes:
        elastic: the 18 moduli (the closed-form model needs ``tau = sigma = 0`` and only
            ``tau7`` of the taus nonzero: decoupled levels, module docstring; the iterative
            model, :mod:`granfe.models.micromorphic_iterative`, takes any).
        macro: cone of the macro stress ``S`` [Pa].
        micro: cone of the symmetric relative stress ``sym(s - sigma)`` [Pa].
        gradient: cone of each slice ``m_..M`` of the higher-order stress [Pa m].
    """

    elastic: MicromorphicMaterial
    macro: Cone | None = None
    micro: Cone | None = None
    gradient: Cone | None = None

    def __post_init__(self):
        if not isinstance(self.elastic, MicromorphicMaterial):
            raise TypeError("MicromorphicDruckerPragerMaterial.elastic must be a MicromorphicMaterial")
        for level in LEVELS:
            cone = getattr(self, level)
            if cone is not None and not isinstance(cone, Cone):
                raise TypeError(f"MicromorphicDruckerPragerMaterial.{level} must be a Cone or None")

    @property
    def active(self) -> tuple[str, ...]:
        return tuple(level for level in LEVELS if getattr(self, level) is not None)


def _check_decoupled(material) -> None:
    coupled = [k for k in ("tau", "sigma") + _ZERO_TAUS if getattr(material.elastic, k) != 0.0]
    if coupled:
        raise ValueError(f"MicromorphicDruckerPragerMaterial.elastic: {', '.join(coupled)} "
                         "must be 0 for the closed-form returns (decoupled levels: D = 0, "
                         "C = tau7 I); the micromorphic_drucker_prager_iterative model returns "
                         "at the points for any moduli")


def cone_return(dev_tr, p_tr, G, K, A, B, k0, H, eq):
    """Radial return of a trial stress to ``sqrt(J2) + A p - (k0 + H e_q) <= 0`` (UFL).

    Args:
        dev_tr, p_tr: deviatoric (3 x 3) and mean trial stress (tension positive).
        G, K: the level's moduli (``dev t = 2 G dev e``, ``p = K tr e``).
        A, B, k0, H: friction, dilatancy, strength and hardening of the cone.
        eq: committed equivalent plastic strain.

    Returns:
        dict of ``dev``, ``p`` (returned stress), ``d_plastic`` (3 x 3 plastic strain
        increment), ``d_eq`` and ``f_trial``. At the apex the deviator vanishes; without
        dilatancy or hardening the stress is put there by volumetric plastic strain, which
        stands for the indeterminate multiplier (as in
        :class:`~granfe.models.drucker_prager.MicropolarDruckerPrager`).
    """
    tau_tr = ufl.sqrt(0.5 * ufl.inner(dev_tr, dev_tr) + 1e-30)
    k = k0 + H * eq
    f_tr = tau_tr + A * p_tr - k
    dl_cone = ufl.conditional(f_tr > 0, f_tr / (G + K * A * B + H), 0.0)
    apex = ufl.And(f_tr > 0, tau_tr - G * dl_cone < 0)
    stiff = K * A * B + H
    dl_apex = ufl.conditional(stiff > 0, (A * p_tr - k) / ufl.max_value(stiff, 1e-300),
                              (p_tr - k / ufl.max_value(A, 1e-300)) / K)
    p_apex = ufl.conditional(stiff > 0, p_tr - K * B * dl_apex, k / ufl.max_value(A, 1e-300))
    scale = ufl.conditional(apex, 0.0, 1 - G * dl_cone / tau_tr)
    p = ufl.conditional(apex, p_apex, p_tr - K * B * dl_cone)
    d_plastic = (1 - scale) * dev_tr / (2 * G) + (p_tr - p) / (3 * K) * ufl.Identity(3)
    d_eq = ufl.conditional(apex, dl_apex + tau_tr / G, dl_cone)
    return {"dev": scale * dev_tr, "p": p, "d_plastic": d_plastic, "d_eq": d_eq, "f_trial": f_tr}


def _to3(t, gdim):
    if gdim == 3:
        return t
    return ufl.as_matrix([[t[0, 0], t[0, 1], 0], [t[1, 0], t[1, 1], 0], [0, 0, 0]])


def _from3(t, gdim):
    return ufl.as_matrix([[t[i, j] for j in range(gdim)] for i in range(gdim)])


class MicromorphicDruckerPrager(Micromorphic):
    """Three-level micromorphic Drucker-Prager plasticity with a
    :class:`MicromorphicDruckerPragerMaterial` (module docstring)."""

    name = "micromorphic_drucker_prager"
    linear = False
    material_type = MicromorphicDruckerPragerMaterial
    # as MicropolarDruckerPrager: a step starts from a converged state whose residual is the
    # boundary increment only, so no divergence test and no line search
    solver_options = {"snes_max_it": 50, "snes_divergence_tolerance": 1e300}
    # five returns (macro, micro, three slices) in every kernel: the 3D triaxial problem's
    # forms and state expressions compile in ~7 s CPU at -O0, ~20 s at gcc's default
    jit_options: ClassVar[dict] = {"cffi_extra_compile_args": ["-O0", "-g0"]}

    def __init__(self, material):
        super().__init__(material)
        self.active = material.active
        _check_decoupled(material)

    def update(self, material) -> None:
        if isinstance(material, self.material_type) and material.active != self.active:
            raise ValueError(f"the plastic levels are fixed when the forms are built: "
                             f"{self.active}, the new material has {material.active}")
        _check_decoupled(material)
        super().update(material)

    def constant_values(self, material):
        values = super().constant_values(material.elastic)
        for level in LEVELS:
            cone = getattr(material, level) or Cone(1.0, 0.0)   # placeholder of an elastic level
            A, B, k0 = cone.constants
            values.update({f"{level}_A": A, f"{level}_B": B, f"{level}_k0": k0,
                           f"{level}_H": float(cone.hardening)})
        return values

    def state_variables(self, gdim):
        return {"plastic_strain": (3, 3), "plastic_micro_strain": (3, 3),
                "plastic_micro_gradient": (gdim, 3, 3),
                "equivalent_plastic_strain": (2 + gdim,), "yielding": (3,)}

    # ---- the return mapping ---------------------------------------------------------
    def _level(self, level, dev_tr, p_tr, eq):
        """The return of one level, or the elastic trial state when it has no cone."""
        if level not in self.active:
            return {"dev": dev_tr, "p": p_tr, "d_plastic": ufl.zero(3, 3), "d_eq": 0.0,
                    "f_trial": ufl.as_ufl(-1.0)}
        c = self.constants
        G, K = self._moduli(level)
        return cone_return(dev_tr, p_tr, G, K, getattr(c, f"{level}_A"), getattr(c, f"{level}_B"),
                           getattr(c, f"{level}_k0"), getattr(c, f"{level}_H"), eq)

    def _moduli(self, level):
        """``(G, K)`` of a level: its deviatoric and volumetric stiffness (module docstring)."""
        c = self.constants
        return {"macro": (c.mu, c.lam + 2 * c.mu / 3),
                "micro": ((c.kappa + c.nu) / 2, c.eta + (c.kappa + c.nu) / 3),
                "gradient": (c.tau7 / 2, c.tau7 / 3)}[level]

    def _return(self, w, state):
        """Trial stresses of every level from the committed plastic parts, and their returns.

        Returns a dict of the stresses ``S`` (3 x 3), ``T`` and ``m`` (gdim blocks), the trial
        yield values and the updated state."""
        c = self.constants
        u, phi = self._split(w)
        gdim = ufl.shape(u)[0]
        eps, E, G = strains(u, phi)
        eq = state["equivalent_plastic_strain"]
        I3 = ufl.Identity(3)
        # macro: S of the elastic macro strain
        eps_e = _to3(eps, gdim) - state["plastic_strain"]
        G1, K1 = self._moduli("macro")
        macro = self._level("macro", 2 * G1 * ufl.dev(eps_e), K1 * ufl.tr(eps_e), eq[0])
        S = macro["dev"] + macro["p"] * I3
        # micro: the symmetric relative stress; its skew part is elastic
        E_e = _to3(E, gdim) - state["plastic_micro_strain"]
        G2, K2 = self._moduli("micro")
        micro = self._level("micro", 2 * G2 * ufl.dev(ufl.sym(E_e)), K2 * ufl.tr(E_e), eq[1])
        T = micro["dev"] + micro["p"] * I3 + (c.kappa - c.nu) * ufl.skew(E_e)
        # higher order: one cone per slice m_..M
        Gp = state["plastic_micro_gradient"]
        G3, K3 = self._moduli("gradient")
        slices = []
        for M in range(gdim):
            Ge = _to3(ufl.as_matrix([[G[k, l, M] for l in range(gdim)] for k in range(gdim)]), gdim)
            Ge = Ge - ufl.as_matrix([[Gp[M, k, l] for l in range(3)] for k in range(3)])
            slices.append(self._level("gradient", 2 * G3 * ufl.dev(Ge), K3 * ufl.tr(Ge), eq[2 + M]))
        m_slices = [r["dev"] + r["p"] * I3 for r in slices]
        m = ufl.as_tensor([[[m_slices[M][k, l] for M in range(gdim)] for l in range(gdim)]
                           for k in range(gdim)])
        flag = lambda f: ufl.conditional(f > 0, 1.0, 0.0)  # noqa: E731
        any_slice = sum(flag(r["f_trial"]) for r in slices)
        new_eq = [eq[0] + macro["d_eq"], eq[1] + micro["d_eq"]] + [
            eq[2 + M] + r["d_eq"] for M, r in enumerate(slices)]
        return {
            "S": S, "T": _from3(T, gdim), "m": m,
            "f_trial": (macro["f_trial"], micro["f_trial"], [r["f_trial"] for r in slices]),
            "plastic_strain": state["plastic_strain"] + macro["d_plastic"],
            "plastic_micro_strain": state["plastic_micro_strain"] + micro["d_plastic"],
            "plastic_micro_gradient": ufl.as_tensor(
                [[[Gp[M, k, l] + slices[M]["d_plastic"][k, l] for l in range(3)]
                  for k in range(3)] for M in range(gdim)]),
            "equivalent_plastic_strain": ufl.as_vector(new_eq),
            "yielding": ufl.as_vector([flag(macro["f_trial"]), flag(micro["f_trial"]),
                                       ufl.conditional(any_slice > 0, 1.0, 0.0)]),
        }

    def state_update(self, w, state):
        r = self._return(w, state)
        return {k: r[k] for k in self.state_variables(ufl.shape(w[0])[0])}

    def stresses(self, w, state):
        """``sigma = S + T^T``, ``s = S + T + T^T`` and ``m`` of the returned state, and the
        relative stress ``T = s - sigma``."""
        r = self._return(w, state)
        gdim = ufl.shape(w[0])[0]
        S, T = _from3(r["S"], gdim), r["T"]
        return {"sigma": S + T.T, "micro_stress": S + T + T.T, "higher_order_stress": r["m"],
                "relative_stress": T}

    def internal_work(self, w, dw, state):
        """``S : eps(du) + T : E(du, dphi) + m : grad dphi`` (the virtual work of
        :class:`~granfe.models.micromorphic.Micromorphic` in the conjugates of the measures)."""
        r = self._return(w, state)
        gdim = ufl.shape(w[0])[0]
        eps, E, G = strains(*self._split(dw))
        return ufl.inner(_from3(r["S"], gdim), eps) + ufl.inner(r["T"], E) + ufl.inner(r["m"], G)

    def stored_energy(self, w, state):
        """The energy of the elastic parts of the three measures."""
        c = self.constants
        u, phi = self._split(w)
        gdim = ufl.shape(u)[0]
        eps, E, G = strains(u, phi)
        eps_e = _to3(eps, gdim) - state["plastic_strain"]
        E_e = _to3(E, gdim) - state["plastic_micro_strain"]
        Gp = state["plastic_micro_gradient"]
        W = (c.lam / 2 * ufl.tr(eps_e) ** 2 + c.mu * ufl.inner(eps_e, eps_e)
             + c.eta / 2 * ufl.tr(E_e) ** 2 + c.kappa / 2 * ufl.inner(E_e, E_e)
             + c.nu / 2 * ufl.inner(E_e, E_e.T))
        for M in range(gdim):
            Ge = _to3(ufl.as_matrix([[G[k, l, M] for l in range(gdim)] for k in range(gdim)]), gdim)
            Ge = Ge - ufl.as_matrix([[Gp[M, k, l] for l in range(3)] for k in range(3)])
            W += c.tau7 / 2 * ufl.inner(Ge, Ge)
        return W
