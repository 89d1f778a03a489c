"""Micropolar (Cosserat) Drucker-Prager elastoplasticity, small strain (de Borst 1993).

Fields and elasticity are those of :mod:`granfe.models.micropolar`. Plastic flow acts on
the symmetric part of the force stress and on the couple stress; the skew part of the
force stress stays elastic. With ``s`` the deviator of ``sym sigma`` (3 x 3, so that in
plane strain the out-of-plane stress and plastic strain are kept) and ``p = tr sigma / 3``
(tension positive), the yield function and plastic potential are::

    f = tau + A p - k(e_q),     g = tau + B p,     k(e_q) = max(k0 + H e_q, k_r),
    tau = sqrt(J2),  J2 = 1/2 s:s + 1/2 m:m / l^2,   l^2 = gamma / (2 G),

with ``G = mu + kappa / 2`` the classical shear modulus. That plastic length makes the
return mapping radial: the deviatoric force stress and the couple stress are scaled by the
same factor ``1 - G dl / tau_trial``, so the whole update is closed form (UFL conditionals)
and SNES gets the consistent tangent from ``ufl.derivative``. Where the radial return
would cross the cone's apex the stress returns to the apex. Constant ``A, B, k0`` come
from a Mohr-Coulomb friction angle, dilatancy angle and cohesion through a stated match
(:class:`DruckerPragerMaterial`); ``k_r`` from the residual cohesion, the floor of linear
softening (``H < 0``): past ``e_q = (k0 - k_r) / -H`` the cone stays put (a negative
cohesion would put the apex on the compression side). Quadrature-point state: plastic
strain (3 x 3), plastic curvature, equivalent plastic strain ``e_q`` (the accumulated
multiplier), and the yield indicator of the last committed step.

Couple stress elasticity in the plastic model is gamma only (``alpha = beta = 0``): the
radial return needs the curvature energy to be ``gamma/2 kap:kap``.

Initial stress: a uniform ``sigma_0 = diag(initial_stress)`` (3 x 3, tension positive) in
equilibrium with loads that are not modelled (a chamber consolidated under its boundary
stresses, the window's grains carrying the same). The yield function sees the total stress
``sigma_0 + sigma(eps - eps_p)``; the equations carry the increment (the internal work is
that of ``sigma - sigma_0``), so the boundary conditions are those of the increment, as for
the elastic continuum around a consolidated DE window.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import dolfinx_solver  # noqa: F401

import numba
import numpy as np
import ufl

from granfe.materials import MicropolarMaterial
from granfe.models.base import ContinuumModel
from granfe.models.micropolar import Micropolar, curvature, strain

__all__ = ["DruckerPragerMaterial", "MicropolarDruckerPrager", "drucker_prager_constants"]

MATCHES = ("triaxial_compression", "plane_strain")


def drucker_prager_constants(friction_deg: float, dilatancy_deg: float, cohesion: float,
                             match: str) -> tuple[float, float, float]:
    """``(A, B, k0)`` of ``f = sqrt(J2) + A p - k0`` matched to Mohr-Coulomb ``(c, phi, psi)``.

    ``triaxial_compression``: the cone through the Mohr-Coulomb compression meridian
    (3D triaxial compression peaks at ``sigma_1 = sigma_3 tan^2(45 + phi/2) + 2 c
    tan(45 + phi/2)``). ``plane_strain``: the cone that gives Mohr-Coulomb's collapse
    stresses in plane strain when the out-of-plane plastic strain rate is zero (for any
    dilatancy; for psi = phi it is the familiar ``A = 3 tan phi / sqrt(9 + 12 tan^2 phi)``),
    so that a plane-strain collapse load compares with Mohr-Coulomb solutions (Prandtl).
    """
    if match not in MATCHES:
        raise ValueError(f"match must be one of {MATCHES}, got {match!r}")
    phi, psi = math.radians(friction_deg), math.radians(dilatancy_deg)
    if match == "triaxial_compression":
        A = 2 * math.sqrt(3) * math.sin(phi) / (3 - math.sin(phi))
        B = 2 * math.sqrt(3) * math.sin(psi) / (3 - math.sin(psi))
        k0 = 2 * math.sqrt(3) * cohesion * math.cos(phi) / (3 - math.sin(phi))
        return A, B, k0
    # plane strain: zero out-of-plane plastic strain rate gives s_zz = -2 B tau / 3, so
    # tau = t / D with t the in-plane maximum shear stress and D = sqrt(1 - B^2 / 3);
    # the dilatancy ratio of the flow, B / D, is sin(psi)
    B = math.sin(psi) / math.sqrt(1 + math.sin(psi) ** 2 / 3)
    D = math.sqrt(1 - B**2 / 3)
    A = math.sin(phi) / (D + math.sin(phi) * B / 3)
    k0 = cohesion * math.cos(phi) * (1 - A * B / 3) / D
    return A, B, k0


@dataclass(frozen=True)
class DruckerPragerMaterial:
    """Micropolar elasticity plus a Drucker-Prager cone matched to Mohr-Coulomb.

    Attributes:
        elastic: the micropolar elastic constants (``alpha = beta = 0``).
        cohesion: c [Pa] (>= 0).
        friction_deg: phi [deg] in [0, 90).
        dilatancy_deg: psi [deg] in [0, phi] (non-associated below phi).
        hardening: H [Pa] per unit equivalent plastic strain (negative softens).
        match: ``"triaxial_compression"`` (3D) or ``"plane_strain"`` (2D), see
            :func:`drucker_prager_constants`.
        residual_cohesion: c_r [Pa] in [0, cohesion], where softening stops (the cone of
            friction phi and cohesion c_r); unused when hardening >= 0.
        initial_stress: (sigma_xx, sigma_yy, sigma_zz) [Pa] of a uniform initial stress
            (tension positive; in plane strain sigma_zz is the out-of-plane one), see the
            module docstring; it must lie inside the cone.
    """

    elastic: MicropolarMaterial
    cohesion: float
    friction_deg: float
    dilatancy_deg: float = 0.0
    hardening: float = 0.0
    match: str = "plane_strain"
    residual_cohesion: float = 0.0
    initial_stress: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self):
        if not isinstance(self.elastic, MicropolarMaterial):
            raise TypeError("DruckerPragerMaterial.elastic must be a MicropolarMaterial")
        e = self.elastic
        if e.alpha != 0.0 or e.beta != 0.0:
            raise ValueError("DruckerPragerMaterial.elastic: alpha and beta must be 0 (the "
                             "closed-form return needs a gamma-only couple-stress energy)")
        checks = (
            ("cohesion", self.cohesion >= 0, ">= 0 Pa"),
            ("friction_deg", 0 <= self.friction_deg < 90, "in [0, 90) degrees"),
            ("dilatancy_deg", 0 <= self.dilatancy_deg <= self.friction_deg,
             "in [0, friction_deg] degrees"),
            ("hardening", math.isfinite(self.hardening), "finite"),
            ("residual_cohesion", 0 <= self.residual_cohesion <= self.cohesion,
             "in [0, cohesion] Pa"),
        )
        for name, ok, rule in checks:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and ok):
                raise ValueError(f"DruckerPragerMaterial.{name} must be {rule}, got {value!r}")
        if self.match not in MATCHES:
            raise ValueError(f"DruckerPragerMaterial.match must be one of {MATCHES}, "
                             f"got {self.match!r}")
        A, _, k0 = self.constants
        if A == 0 and k0 == 0:
            raise ValueError("DruckerPragerMaterial: cohesion 0 with friction 0 has no strength")
        G = e.mu + e.kappa / 2
        if self.hardening <= -G:
            raise ValueError(f"DruckerPragerMaterial.hardening must be > -G = {-G!r} Pa")
        s0 = tuple(self.initial_stress)
        if len(s0) != 3 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in s0):
            raise ValueError("DruckerPragerMaterial.initial_stress must be three finite numbers "
                             f"(sigma_xx, sigma_yy, sigma_zz) [Pa], got {self.initial_stress!r}")
        p0 = sum(s0) / 3
        tau0 = math.sqrt(0.5 * sum((v - p0) ** 2 for v in s0))
        if tau0 + A * p0 - k0 > 1e-12 * max(abs(k0), abs(A * p0), 1.0):
            raise ValueError(f"DruckerPragerMaterial.initial_stress {s0} lies outside the yield "
                             f"cone (sqrt(J2) + A p - k = {tau0 + A * p0 - k0:.4g} Pa > 0): more "
                             "friction or cohesion, or a less deviatoric initial stress")

    @property
    def constants(self) -> tuple[float, float, float]:
        """``(A, B, k0)``: friction and dilatancy coefficients and the cone's strength [Pa]."""
        return drucker_prager_constants(self.friction_deg, self.dilatancy_deg, self.cohesion,
                                        self.match)

    @property
    def residual_strength(self) -> float:
        """``k_r``: the cone's strength [Pa] once softening has used up ``cohesion - c_r``."""
        return drucker_prager_constants(self.friction_deg, self.dilatancy_deg,
                                        self.residual_cohesion, self.match)[2]

    @property
    def shear_modulus(self) -> float:
        return self.elastic.mu + self.elastic.kappa / 2

    @property
    def bulk_modulus(self) -> float:
        e = self.elastic
        return e.lam + 2 * self.shear_modulus / 3


def _to3(t, gdim):
    """A gdim x gdim tensor embedded in 3 x 3 (plane strain: zeros out of plane)."""
    if gdim == 3:
        return t
    return ufl.as_matrix([[t[0, 0], t[0, 1], 0], [t[1, 0], t[1, 1], 0], [0, 0, 0]])


def _from3(t, gdim):
    if gdim == 3:
        return t
    return ufl.as_matrix([[t[0, 0], t[0, 1]], [t[1, 0], t[1, 1]]])


class MicropolarDruckerPrager(Micropolar):
    """Micropolar Drucker-Prager elastoplasticity with a :class:`DruckerPragerMaterial`."""

    name = "micropolar_drucker_prager"
    linear = False
    material_type = DruckerPragerMaterial
    # no divergence test: a step starts from a converged state whose residual is only the
    # boundary increment (x - g on the Dirichlet rows), orders of magnitude below the force
    # residual of the first iterate; for the same reason no line search (it would compare
    # the two and shrink every step)
    solver_options = {"snes_max_it": 50, "snes_divergence_tolerance": 1e300}
    #: Newton's first iteration of a step takes the elastic-plastic tangent of the last
    #: committed step (see :meth:`_return`); False: the tangent of the trial return, elastic
    #: wherever round-off puts a yielding point's trial value below the cone
    tangent_predictor = True

    def constant_values(self, material):
        values = super().constant_values(material.elastic)
        A, B, k0 = material.constants
        values.update(A=A, B=B, k0=k0, H=material.hardening, k_r=material.residual_strength)
        values.update({f"s0_{k}": float(v) for k, v in zip("xyz", material.initial_stress, strict=True)})
        return values

    def _initial_stress(self):
        c = self.constants
        return ufl.diag(ufl.as_vector([c.s0_x, c.s0_y, c.s0_z]))

    def make_constants(self, domain):
        # the namespace of every constant (the micropolar dataclass holds the elastic ones only)
        return ContinuumModel.make_constants(self, domain)

    def state_variables(self, gdim):
        return {"plastic_strain": (3, 3), "plastic_curvature": (2,) if gdim == 2 else (3, 3),
                "equivalent_plastic_strain": (), "yielding": ()}

    # ---- the return mapping ---------------------------------------------------------
    def _return(self, w, state):
        """Trial stresses from the committed plastic state, and their return to the cone.

        Returns a dict of the updated stresses (gdim blocks) and plastic increments."""
        c = self.constants
        u, phi = w
        gdim = ufl.shape(u)[0]
        G = c.mu + c.kappa / 2
        K = c.lam + 2 * G / 3
        I3 = ufl.Identity(3)
        eps = _to3(strain(u, phi), gdim)
        eps_e = eps - state["plastic_strain"]
        sym_e, skw_e = ufl.sym(eps_e), ufl.skew(eps_e)
        vol = ufl.tr(eps_e)
        kap_e = curvature(phi) - state["plastic_curvature"]
        s0 = self._initial_stress()
        s_tr = 2 * G * ufl.dev(sym_e) + ufl.dev(s0)
        p_tr = K * vol + ufl.tr(s0) / 3
        m_tr = c.gamma * kap_e
        l2 = c.gamma / (2 * G)
        tau_tr = ufl.sqrt(0.5 * ufl.inner(s_tr, s_tr) + 0.5 * ufl.inner(m_tr, m_tr) / l2 + 1e-30)
        eq = state["equivalent_plastic_strain"]
        k_lin = c.k0 + c.H * eq
        k = ufl.max_value(k_lin, c.k_r)
        f_tr = tau_tr + c.A * p_tr - k
        # a point that yielded in the last committed step returns also when its trial value is
        # below zero by round-off only: at the start of a step (the fields of the last converged
        # state) such a point sits on the cone to round-off, so that Newton's first iteration
        # takes the elastic-plastic tangent of the last step (the tangent predictor) instead of
        # the elastic one at the points that land below zero (the return moves the stress by
        # at most that round-off)
        on_cone = 1e-12 * (abs(k) + abs(c.A * p_tr) + tau_tr)
        plastic = f_tr > 0
        if self.tangent_predictor:
            plastic = ufl.Or(plastic, ufl.And(state["yielding"] > 0.5, f_tr > -on_cone))
        # k(e_q + dl) = max(linear, floor): f(dl) is the smaller of the two branches' (both
        # decreasing in dl), so its root is the smaller of their roots, for either sign of H
        dl_lin = (tau_tr + c.A * p_tr - k_lin) / (G + K * c.A * c.B + c.H)
        dl_floor = (tau_tr + c.A * p_tr - c.k_r) / (G + K * c.A * c.B)
        dl_cone = ufl.conditional(plastic, ufl.min_value(dl_lin, dl_floor), 0.0)
        apex = ufl.And(plastic, tau_tr - G * dl_cone < 0)
        # apex: the deviatoric and couple stresses vanish, the mean stress meets the cone
        # (without dilatancy or hardening the apex is reached by no flow: the mean stress is
        # put on the apex, p = k / A); the hardening modulus of the branch the step starts on
        H = ufl.conditional(k_lin > c.k_r, c.H, 0.0)
        stiff = K * c.A * c.B + H
        # without dilatancy or hardening the multiplier at the apex is indeterminate (the
        # stress is put there by no flow): the volumetric plastic strain stands for it (a
        # division by the vanishing stiffness made it ~1e305 per step, inf after a few hundred,
        # and H * inf a NaN in the yield stress)
        dl_apex = ufl.conditional(stiff > 0, (c.A * p_tr - k) / ufl.max_value(stiff, 1e-300),
                                  (p_tr - k / ufl.max_value(c.A, 1e-300)) / K)
        scale = ufl.conditional(apex, 0.0, 1 - G * dl_cone / tau_tr)
        dl = ufl.conditional(apex, dl_apex, dl_cone)
        p_apex = ufl.conditional(stiff > 0, p_tr - K * c.B * dl_apex,
                                 k / ufl.max_value(c.A, 1e-300))
        p = ufl.conditional(apex, p_apex, p_tr - K * c.B * dl_cone)
        s, m = scale * s_tr, scale * m_tr
        d_plastic_dev = (1 - scale) * s_tr / (2 * G)
        d_curv = (1 - scale) * kap_e
        sigma3 = s + p * I3 + c.kappa * skw_e
        return {
            "sigma": _from3(sigma3, gdim), "m": m, "f_trial": f_tr,
            "plastic_strain": state["plastic_strain"] + d_plastic_dev + (p_tr - p) / (3 * K) * I3,
            "plastic_curvature": state["plastic_curvature"] + d_curv,
            "equivalent_plastic_strain": eq + ufl.conditional(apex, dl + tau_tr / G, dl),
            "yielding": ufl.conditional(plastic, 1.0, 0.0),
        }

    def state_update(self, w, state):
        r = self._return(w, state)
        return {k: r[k] for k in self.state_variables(ufl.shape(w[0])[0])}

    def stresses(self, w, state):
        """The total stresses (with the initial stress)."""
        r = self._return(w, state)
        return {"sigma": r["sigma"], "couple_stress": r["m"]}

    def internal_work(self, w, dw, state):
        """Work of the stress increment from the initial stress (module docstring)."""
        r = self._return(w, state)
        gdim = ufl.shape(w[0])[0]
        sigma = r["sigma"] - _from3(self._initial_stress(), gdim)
        return ufl.inner(sigma, strain(*dw)) + ufl.inner(r["m"], curvature(dw[1]))

    def elastic_work(self, w, dw):
        """Virtual work of the elastic stresses of ``w`` (micropolar): :meth:`internal_work`'s
        derivative wherever no point yields. It does not change with the state, so a time
        stepper may factorise its Jacobian once (:class:`granfe.dynamics.GeneralizedAlpha`)."""
        return Micropolar.internal_work(self, w, dw, {})

    def stored_energy(self, w, state):
        """Elastic energy of the elastic strains (the stored part of the work)."""
        c = self.constants
        u, phi = w
        gdim = ufl.shape(u)[0]
        G = c.mu + c.kappa / 2
        eps_e = _to3(strain(u, phi), gdim) - state["plastic_strain"]
        kap_e = curvature(phi) - state["plastic_curvature"]
        sym_e = ufl.sym(eps_e)
        return (c.lam / 2 * ufl.tr(eps_e) ** 2 + G * ufl.inner(sym_e, sym_e)
                + c.kappa / 2 * ufl.inner(ufl.skew(eps_e), ufl.skew(eps_e))
                + c.gamma / 2 * ufl.inner(kap_e, kap_e))

    # ---- the same return in a fused kernel (numba), for explicit steps ----------------
    # An explicit step needs the stress once per step, not its derivative: on degree-1
    # simplices one pass over the cells (kinematics, this return, the element forces) costs
    # a fraction of the UFL return compiled into the residual and the state update
    # (benchmarks/plastic_cost.py). The return in _element_forces is the UFL return's twin,
    # line for line; tests/granfe/test_explicit.py holds them equal on every branch.
    def _point_constants(self) -> np.ndarray:
        c = self.constants
        return np.array([float(getattr(c, k).value) for k in
                         ("lam", "mu", "kappa", "gamma", "A", "B", "k0", "H", "k_r", "s0_x", "s0_y", "s0_z")])

    def simplex_forces(self, cells, w: np.ndarray, state: dict, new_state: dict, f: np.ndarray) -> None:
        """The internal forces on degree-1 simplices in one pass (kinematics, return, element
        forces), added into ``f`` (local dofs): the residual of :meth:`internal_work` with
        the return of :meth:`state_update` committed. ``cells``: the geometry of
        :class:`granfe.explicit.SimplexCells`; ``state`` / ``new_state``: name -> the owned
        points' values, one row a point in the order of the cells' points (``new_state`` may
        be ``state``)."""
        nk = 2 if cells.gdim == 2 else 9
        P = cells.wdet.size

        def flat(a, n):
            return a.reshape(P, n) if n else a.reshape(P)

        _element_forces_kernel(cells.gdim)(cells.grads, cells.wdet, cells.N, cells.dofs["u"], cells.dofs["phi"], w,
                        self._point_constants(), bool(self.tangent_predictor),
                        flat(state["plastic_strain"], 9), flat(state["plastic_curvature"], nk),
                        flat(state["equivalent_plastic_strain"], 0), flat(state["yielding"], 0),
                        flat(new_state["plastic_strain"], 9), flat(new_state["plastic_curvature"], nk),
                        flat(new_state["equivalent_plastic_strain"], 0), flat(new_state["yielding"], 0), f)


@functools.cache
def _element_forces_kernel(gdim: int):  # noqa: C901
    """:func:`_element_forces` compiled for ``gdim`` (2 or 3) as a constant: the loops over
    vertices, components and points have fixed trip counts and unroll (the 3D chamber's
    kernel 2x faster than with the dimension read from the arrays). Each dimension's kernel
    is cached under its own name (numba keys its disk cache by the function's name)."""

    def _element_forces(grads, wdet, N, dofs_u, dofs_phi, w, c, predictor, eps_p, kap_p, eq,  # noqa: C901
                        yielding, eps_p_new, kap_p_new, eq_new, yielding_new, f):
        """The internal forces of the micropolar Drucker-Prager continuum on degree-1 simplices,
        the return at each point from the committed state: added into ``f`` (the local dofs).

        Per cell ``c``: the basis gradients ``grads[c]`` (vertices x gdim, constant on a
        simplex), ``wdet[c]`` the quadrature weights times |det J| (and the partition weight),
        ``N`` the basis at the points (points x vertices), ``dofs_u[c]`` / ``dofs_phi[c]``
        (vertices x components) the local dofs of u and phi. The state arrays hold point
        ``c * points + q`` in row ``c * points + q``. Strain ``grad u + e.phi``, curvature
        ``grad phi`` (:mod:`granfe.models.micropolar`), the work of ``sigma - sigma_0``. The new
        state may overwrite the old: each value is read before it is written."""
        nc = grads.shape[0]
        nv = gdim + 1
        nq = N.shape[0]
        nphi = 1 if gdim == 2 else 3
        nk = nphi * gdim
        lam, mu, kappa, gamma, A, B, k0, H, k_r = c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8]
        G = mu + kappa / 2
        K = lam + 2 * G / 3
        l2 = gamma / (2 * G)
        ps0 = (c[9] + c[10] + c[11]) / 3
        kin, sig, m = np.empty((1, 9 + nk)), np.empty((1, 9)), np.empty((1, nk))
        e, s_tr = np.empty(9), np.empty(9)
        gu = np.zeros(9)
        phi, t = np.zeros(3), np.zeros(3)
        S, Msum, T = np.zeros(9), np.zeros(nk), np.zeros((nv, nphi))
        for cell in range(nc):
            for i in range(9):
                gu[i] = 0.0
                S[i] = 0.0
            for i in range(nk):
                Msum[i] = 0.0
            T[:, :] = 0.0
            for i in range(gdim):
                for j in range(gdim):
                    acc = 0.0
                    for a in range(nv):
                        acc += w[dofs_u[cell, a, i]] * grads[cell, a, j]
                    gu[3 * i + j] = acc
            for i in range(nphi):
                for j in range(gdim):
                    acc = 0.0
                    for a in range(nv):
                        acc += w[dofs_phi[cell, a, i]] * grads[cell, a, j]
                    kin[0, 9 + i * gdim + j] = acc
            for qi in range(nq):
                for kk in range(nphi):
                    acc = 0.0
                    for a in range(nv):
                        acc += N[qi, a] * w[dofs_phi[cell, a, kk]]
                    phi[kk] = acc
                for i in range(9):
                    kin[0, i] = gu[i]
                if gdim == 2:
                    kin[0, 1] += phi[0]
                    kin[0, 3] -= phi[0]
                else:
                    kin[0, 1] += phi[2]
                    kin[0, 2] -= phi[1]
                    kin[0, 3] -= phi[2]
                    kin[0, 5] += phi[0]
                    kin[0, 6] += phi[1]
                    kin[0, 7] -= phi[0]
                # the return at point q (MicropolarDruckerPrager._return; its comments say why),
                # inline: a call per point passing arrays costs ~0.4 us in reference counts (10x)
                q = cell * nq + qi
                for i in range(9):
                    e[i] = kin[0, i] - eps_p[q, i]
                vol = e[0] + e[4] + e[8]
                ss = 0.0
                for i in range(3):
                    for j in range(3):
                        sym = 0.5 * (e[3 * i + j] + e[3 * j + i])
                        if i == j:
                            s_tr[3 * i + j] = 2 * G * (sym - vol / 3) + (c[9 + i] - ps0)
                        else:
                            s_tr[3 * i + j] = 2 * G * sym
                        ss += s_tr[3 * i + j] ** 2
                mm = 0.0
                for i in range(nk):
                    mm += (gamma * (kin[0, 9 + i] - kap_p[q, i])) ** 2
                p_tr = K * vol + ps0
                tau_tr = np.sqrt(0.5 * ss + 0.5 * mm / l2 + 1e-30)
                k_lin = k0 + H * eq[q]
                k = max(k_lin, k_r)
                f_tr = tau_tr + A * p_tr - k
                on_cone = 1e-12 * (abs(k) + abs(A * p_tr) + tau_tr)
                plastic = f_tr > 0 or (predictor and yielding[q] > 0.5 and f_tr > -on_cone)
                dl_cone = 0.0
                if plastic:
                    dl_lin = (tau_tr + A * p_tr - k_lin) / (G + K * A * B + H)
                    dl_floor = (tau_tr + A * p_tr - k_r) / (G + K * A * B)
                    dl_cone = min(dl_lin, dl_floor)
                apex = plastic and tau_tr - G * dl_cone < 0
                Hb = H if k_lin > k_r else 0.0
                stiff = K * A * B + Hb
                if stiff > 0:
                    dl_apex = (A * p_tr - k) / max(stiff, 1e-300)
                    p_apex = p_tr - K * B * dl_apex
                else:
                    dl_apex = (p_tr - k / max(A, 1e-300)) / K
                    p_apex = k / max(A, 1e-300)
                if apex:
                    scale, dl, p = 0.0, dl_apex, p_apex
                else:
                    scale, dl, p = 1 - G * dl_cone / tau_tr, dl_cone, p_tr - K * B * dl_cone
                for i in range(3):
                    for j in range(3):
                        ij = 3 * i + j
                        skw = 0.5 * (e[ij] - e[3 * j + i])
                        sig[0, ij] = scale * s_tr[ij] + kappa * skw + (p if i == j else 0.0)
                        eps_p_new[q, ij] = (eps_p[q, ij] + (1 - scale) * s_tr[ij] / (2 * G)
                                            + ((p_tr - p) / (3 * K) if i == j else 0.0))
                for i in range(nk):
                    ke = kin[0, 9 + i] - kap_p[q, i]
                    m[0, i] = scale * gamma * ke
                    kap_p_new[q, i] = kap_p[q, i] + (1 - scale) * ke
                eq_new[q] = eq[q] + (dl + tau_tr / G if apex else dl)
                yielding_new[q] = 1.0 if plastic else 0.0
                for i in range(3):
                    sig[0, 4 * i] -= c[9 + i]                  # the work of the increment
                # the gradients are constant on the cell: sum the weighted stresses over its
                # points and contract once (the rotation's term needs the basis at each point)
                wq = wdet[cell, qi]
                for i in range(9):
                    S[i] += wq * sig[0, i]
                for i in range(nk):
                    Msum[i] += wq * m[0, i]
                if gdim == 2:
                    t[0] = sig[0, 1] - sig[0, 3]
                else:
                    t[0], t[1], t[2] = sig[0, 5] - sig[0, 7], sig[0, 6] - sig[0, 2], sig[0, 1] - sig[0, 3]
                for a in range(nv):
                    for kk in range(nphi):
                        T[a, kk] += wq * N[qi, a] * t[kk]
            for a in range(nv):
                for i in range(gdim):
                    acc = 0.0
                    for j in range(gdim):
                        acc += S[3 * i + j] * grads[cell, a, j]
                    f[dofs_u[cell, a, i]] += acc
                for i in range(nphi):
                    acc = T[a, i]
                    for j in range(gdim):
                        acc += Msum[i * gdim + j] * grads[cell, a, j]
                    f[dofs_phi[cell, a, i]] += acc

    _element_forces.__qualname__ = _element_forces.__name__ = f"_element_forces_{gdim}d"
    return numba.njit(cache=True)(_element_forces)
