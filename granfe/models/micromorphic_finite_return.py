"""The return mapping of finite-strain three-level micromorphic Drucker-Prager
elastoplasticity at material points (after Regueiro 2010; numpy / numba, no mesh).

Kinematics. Multiplicative splits of the deformation gradient and of the micro-deformation
into elastic and plastic parts, through an intermediate configuration (barred indices)::

    F = F^e F^p,     chi = chi^e chi^p,

and a third plastic variable for the higher-order level, the plastic micro-deformation
gradient ``G^p[A, J, K]`` (first index intermediate, the others reference; it stands for
``chi^p_AJ,K`` and is evolved by its own flow rule, as Regueiro's plastic micro-gradient).
The elastic measures in the intermediate configuration, from the reference ones of
:mod:`granfe.models.micromorphic_finite` (``C = F^T F``, ``Psi = F^T chi``,
``Gamma_IJK = F_iI chi_iJ,K``; every plastic inverse written ``Fp^-1``, ``chip^-1``)::

    C^e   = Fp^-T C Fp^-1,                 Psi^e = Fp^-T Psi chip^-1,
    Gamma^e_ABC = (Fp^-1_IA Gamma_IJK - Psi^e_AD G^p_DJK) chip^-1_JB Fp^-1_KC,

i.e., for ``G^p = grad chi^p``, ``Gamma^e_ABC = F^e_iA chi^e_iB,C`` with the gradient of
``chi^e = chi chip^-1`` taken in the intermediate configuration (``d/dX Fp^-1``). All are invariant under a superposed
rigid rotation (F -> R F, chi -> R chi, grad chi -> R grad chi), so is everything below.

Energy. The quadratic energy of :mod:`granfe.models.micromorphic_finite` on the elastic
measures, ``psi = W(E^e, Etilde^e, Gamma^e)`` with ``E^e = (C^e - I) / 2``,
``Etilde^e = Psi^e - I``; its partials ``psi_E`` (symmetric), ``T``, ``H`` are ``K x``
with ``x`` the 45-vector of :mod:`granfe.models.micromorphic_return` (``[E^e, Etilde^e,
Gamma^e_..M for M = 0, 1, 2]``, :func:`~granfe.models.micromorphic_return.stiffness`).

Reference stresses (the outputs; same conventions as micromorphic_finite: second index of
S the face, last index of M the gradient direction). At a fixed plastic state psi is a
function of (C, Psi, Gamma); its reference partials are the pull-backs::

    psi_E^ref = Fp^-1 psi_E Fp^-T,
    T^ref     = Fp^-1 (T - H_.AC Z_.AC) chip^-T,     Z_DBC = G^p_DJK chip^-1_JB Fp^-1_KC,
    H^ref_IJK = Fp^-1_IA chip^-1_JB Fp^-1_KC H_ABC,

(``(H_.AC Z_.AC)_ID = H_IAC Z_DAC``: Gamma^e depends on Psi through ``Psi^e G^p``), and S,
Sigma, M follow from them by micromorphic_finite's formulas::

    S = psi_E^ref + C^-1 Psi T^ref^T + (C^-1 Gamma) : H^ref,
    Sigma = psi_E^ref + 2 sym(S - psi_E^ref),     M = H^ref.

With no plastic deformation they are micromorphic_finite's stresses (tests).

Plastic rates and their conjugates. With ``L^p = dFp/dt Fp^-1``, ``L^chi = dchip/dt
chip^-1`` and ``Lhat = (dG^p/dt - L^chi G^p) chip^-1 Fp^-1`` (for ``G^p = grad chi^p``
exactly, the intermediate gradient of ``L^chi``, Regueiro's higher-order plastic velocity
gradient), the dissipation is ``-dpsi/dt`` at fixed (F, chi, grad chi)::

    D = Xi : L^p + Xi^chi : L^chi + Mm : Lhat,
    Xi_MN     = (C^e psi_E)_MN + (Psi^e T^T)_MN + Gamma^e_MAK H_NAK + Gamma^e_IAM H_IAN,
    Xi^chi_BA = (Psi^e^T T)_BA + Gamma^e_IBK H_IAK,
    Mm_BAK    = Psi^e_IB H_IAK,

(Mandel-type stresses of the intermediate configuration; the tests check them against
finite differences of psi). The macro plastic flow moves chi^p with it (``L^chi = D^chi -
L^p``, as the small-strain model's micro measure ``E = grad u^T + phi`` carries the macro
plastic strain), so the three levels' flows ``(D^p, D^chi, Lhat)`` have the conjugates::

    macro  t_1 = sym(Xi - Xi^chi^T)      (-> S = dW/d eps of the small-strain model),
    micro  t_2 = sym(Xi^chi)             (-> sym T),
    slice  t_3+K = Mm_..K, K = 0, 1, 2   (-> m_..K),

each tending to the yield stress of :mod:`granfe.models.micromorphic_drucker_prager` as the
strains vanish. This is where the model differs from Regueiro's (2010) statement as the
open Tardigrade ``micromorphic_elasto_plasticity`` implements it (cones on the intermediate
S, Sigma - S and M, pressure ``C^e : S / 3``, deviator ``S - p C^e^-1``): here the cones
are on the conjugates of the plastic rates, so that (i) the small-strain limit is granfe's
small-strain model (yield on ``dW/d eps``, not on sigma) and (ii) a level's dissipation is
exactly ``dl (sqrt(J2) + B p)``, ``dl k >= 0`` for an associated flow and non-negative on
the cone below its apex for ``B <= A``.

Yield and flow on every level (``t`` 3 x 3, ``p = tr t / 3``, ``tau = sqrt(J2)``; the
constants ``(A, B, k0, H)`` of a :class:`~granfe.models.micromorphic_drucker_prager.Cone`)::

    f = tau + A p - (k0 + H e),    D_i = dl_i n_i,   n = dev t / (2 tau) + B I / 3,

symmetric flows on the macro and micro levels (no plastic spin), all nine components on a
slice. Backward Euler with the exponential map (det F^p and det chi^p stay 1 to round-off
where the flow is isochoric, B = 0)::

    F^p_n+1   = exp(D_1) F^p_n,       chi^p_n+1 = exp(D_2 - D_1) chi^p_n,
    G^p_n+1   = exp(D_2 - D_1) G^p_n + sum_C D_3+C[., A] chi^p_n+1[A, J] F^p_n+1[C, K],
    e_i       += dl_i        (at the apex: dl_i + sqrt 2 |dev D_i|, as the small-strain model).

The unknowns ``(D_i, dl_i)`` of the yielding levels solve, with the flow directions at the
end of the step, the equations of :mod:`granfe.models.micromorphic_return` (cone or apex;
its active-set loop and its decoupled radial return as the predictor): Newton on the
unknowns with a central-difference Jacobian (the residual is a few 3 x 3 products) and
backtracking. The step's dissipation is reported as ``sum_i t_i(n+1) : D_i``. Measured on
random states from committed plastic states, strains 1e-3 to 5e-2, coupled moduli, 96 %
of the levels yielding: 0 failures in 9000 points, 4-10 ms a point (a 2-core machine
under load 2-5; linear systems by :func:`_solve`, LAPACK's threads cost 10-50 ms there).

Consistent tangent: the nominal stresses ``y = [P, Q, R]`` (``P = F S``, ``Q = F T^ref``,
``R_iJK = F_iI M_IJK``: the integrands of the residual against ``[grad du, dphi, grad
dphi]``) as functions of ``x = [grad u, phi, grad phi]`` and the converged unknowns z,
``dy/dx = y_x - y_z R_z^-1 R_x`` (R the return's equations; partials by central
differences; ~3 ms more a yielding point).
:class:`~granfe.models.micromorphic_finite_plastic.MicromorphicFiniteDruckerPrager` runs the
return and the tangent at the quadrature points of a mesh.

The kernel is 3D (3 x 3 blocks, 5 levels); plane strain runs it with the out-of-plane
motion held (:mod:`~granfe.models.micromorphic_finite_plastic`). Not here: plastic spin, an
analytic Jacobian of the return (the differences cost most of its time). The seeds do
not reproduce Regueiro's (2010) equations; the formulation above is derived here and
checked by the tests (tests/granfe/test_micromorphic_finite_plasticity.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from granfe.models.micromorphic_drucker_prager import LEVELS, MicromorphicDruckerPragerMaterial
from granfe.models.micromorphic_return import (
    _PDEV,
    _Q,
    _SYMMETRIC,
    _VEC_I,
    LEVEL_COUNT,
    _after_failure,
    _invariants,
    _level_stress,
    _offsets,
    _predict,
    _revise,
    _warm_starts,
    level_moduli,
    stiffness,
)

__all__ = ["KernelTables", "elastic_energy", "finite_return", "initial_state", "kernel_tables",
           "level_stresses"]


# ---- tables ----------------------------------------------------------------------------

@dataclass(frozen=True)
class KernelTables:
    """The kernel's constants: ``K`` (45 x 45), per level ``cones`` (5, 4: A, B, k0, H),
    ``has_cone`` (5,) and the levels' decoupled moduli ``moduli`` (5, 2: G, K)."""

    K: np.ndarray
    cones: np.ndarray
    has_cone: np.ndarray
    moduli: np.ndarray


def kernel_tables(material: MicromorphicDruckerPragerMaterial) -> KernelTables:
    """:class:`KernelTables` of a material (levels 0 macro, 1 micro, 2-4 the slices)."""
    K = stiffness(material.elastic)
    cones, has_cone = np.zeros((LEVEL_COUNT, 4)), np.zeros(LEVEL_COUNT, dtype=bool)
    for i in range(LEVEL_COUNT):
        cone = getattr(material, LEVELS[min(i, 2)])
        if cone is not None:
            cones[i] = (*cone.constants, cone.hardening)
            has_cone[i] = True
    return KernelTables(K, cones, has_cone, level_moduli(K))


def initial_state(shape: tuple = ()) -> dict:
    """No plastic deformation: ``Fp``, ``chip`` (..., 3, 3) identities, ``Gp`` (..., 3, 3, 3)
    and ``eq`` (..., 5) zeros."""
    eye = np.broadcast_to(np.eye(3), (*shape, 3, 3)).copy()
    return {"Fp": eye, "chip": eye.copy(), "Gp": np.zeros((*shape, 3, 3, 3)),
            "eq": np.zeros((*shape, LEVEL_COUNT))}


# ---- the point kernel ------------------------------------------------------------------

@numba.njit(cache=True)
def _expm_sym(A):
    """The exponential of the symmetric part of a 3 x 3 (eigen-decomposition, exact to round-off)."""
    out = np.zeros((3, 3))
    if not (np.all(np.isfinite(A)) and np.max(np.abs(A)) < 50.0):
        out[:, :] = np.nan                    # a wild Newton trial: no exception, a NaN
        return out
    w, V = np.linalg.eigh(0.5 * (A + A.T))
    for i in range(3):
        for j in range(3):
            for k in range(3):
                out[i, j] += V[i, k] * math.exp(w[k]) * V[j, k]
    return out


@numba.njit(cache=True)
def _inv3(a):
    """Inverse of a 3 x 3 by cofactors; NaN (no exception: a Newton trial may be wild) where
    it is singular or not finite."""
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            i1, i2, j1, j2 = (j + 1) % 3, (j + 2) % 3, (i + 1) % 3, (i + 2) % 3
            out[i, j] = a[i1, j1] * a[i2, j2] - a[i1, j2] * a[i2, j1]
    det = a[0, 0] * out[0, 0] + a[0, 1] * out[1, 0] + a[0, 2] * out[2, 0]
    if det == 0.0 or not np.isfinite(det):
        out[:, :] = np.nan
        return out
    return out / det


@numba.njit(cache=True)
def _solve(A, B):
    """``A^-1 B`` (B: n x m) by Gaussian elimination with partial pivoting, in place of
    LAPACK: no exception on a singular A (NaN instead), and no BLAS threads (LAPACK's least
    squares took 10-50 ms on a 44 x 44 system on a loaded 2-core machine, 20 us here)."""
    n = A.shape[0]
    a, x = A.copy(), B.copy()
    for k in range(n):
        piv = k
        for r in range(k + 1, n):
            if abs(a[r, k]) > abs(a[piv, k]):
                piv = r
        if a[piv, k] == 0.0 or not np.isfinite(a[piv, k]):
            x[:, :] = np.nan
            return x
        if piv != k:
            for c in range(n):
                a[k, c], a[piv, c] = a[piv, c], a[k, c]
            for c in range(x.shape[1]):
                x[k, c], x[piv, c] = x[piv, c], x[k, c]
        for r in range(k + 1, n):
            f = a[r, k] / a[k, k]
            if f != 0.0:
                for c in range(k, n):
                    a[r, c] -= f * a[k, c]
                for c in range(x.shape[1]):
                    x[r, c] -= f * x[k, c]
    for k in range(n - 1, -1, -1):
        for c in range(x.shape[1]):
            v = x[k, c]
            for j in range(k + 1, n):
                v -= a[k, j] * x[j, c]
            x[k, c] = v / a[k, k]
    return x


@numba.njit(cache=True)
def _elastic_measures(C, Psi, Gam, Fp, chip, Gp):
    """``(Ce, Psie, Ge, Z, Fpi, chipi)`` (module docstring)."""
    Fpi, chipi = _inv3(Fp), _inv3(chip)
    Ce = Fpi.T @ C @ Fpi
    Psie = Fpi.T @ Psi @ chipi
    X = np.zeros((3, 3, 3))
    for a in range(3):
        for J in range(3):
            for K in range(3):
                s = 0.0
                for i in range(3):
                    s += Fpi[i, a] * Gam[i, J, K] - Psie[a, i] * Gp[i, J, K]
                X[a, J, K] = s
    Ge, Z = np.zeros((3, 3, 3)), np.zeros((3, 3, 3))
    for a in range(3):
        for b in range(3):
            for c in range(3):
                s, z = 0.0, 0.0
                for J in range(3):
                    for K in range(3):
                        w = chipi[J, b] * Fpi[K, c]
                        s += X[a, J, K] * w
                        z += Gp[a, J, K] * w
                Ge[a, b, c], Z[a, b, c] = s, z
    return Ce, Psie, Ge, Z, Fpi, chipi


@numba.njit(cache=True)
def _partials(Ce, Psie, Ge, K):
    """``(x, psi_E, T, H)``: the 45 measures and the energy's partials ``y = K x``."""
    x = np.empty(45)
    for r in range(3):
        for c in range(3):
            x[3 * r + c] = 0.5 * (Ce[r, c] - (1.0 if r == c else 0.0))
            x[9 + 3 * r + c] = Psie[r, c] - (1.0 if r == c else 0.0)
            for M in range(3):
                x[18 + 9 * M + 3 * r + c] = Ge[r, c, M]
    y = K @ x
    psiE, T, H = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3, 3))
    for r in range(3):
        for c in range(3):
            psiE[r, c], T[r, c] = y[3 * r + c], y[9 + 3 * r + c]
            for M in range(3):
                H[r, c, M] = y[18 + 9 * M + 3 * r + c]
    return x, psiE, T, H


@numba.njit(cache=True)
def _level_vector(Ce, Psie, Ge, psiE, T, H):
    """The levels' stresses in one 45-vector (blocks as the small-strain ``y``): macro
    ``Xi - Xi^chi^T``, micro ``Xi^chi`` (both symmetrised by the level), slices ``Mm_..K``."""
    Xi = Ce @ psiE + Psie @ T.T
    Xc = Psie.T @ T
    for m in range(3):
        for n in range(3):
            s, sc = 0.0, 0.0
            for a in range(3):
                for k in range(3):
                    s += Ge[m, a, k] * H[n, a, k] + Ge[a, k, m] * H[a, k, n]
                    sc += Ge[a, m, k] * H[a, n, k]
            Xi[m, n] += s
            Xc[m, n] += sc
    t = np.empty(45)
    for m in range(3):
        for n in range(3):
            t[3 * m + n] = Xi[m, n] - Xc[n, m]
            t[9 + 3 * m + n] = Xc[m, n]
            for K in range(3):
                s = 0.0
                for i in range(3):
                    s += Psie[i, m] * H[i, n, K]
                t[18 + 9 * K + 3 * m + n] = s
    return t


@numba.njit(cache=True)
def _advance(z, modes, dims, offsets, Fp_n, chip_n, Gp_n, Q):
    """The plastic state at the end of the step and the increments ``D`` (5, 3, 3)."""
    D = np.zeros((5, 3, 3))
    for i in range(5):
        if modes[i] == 0:
            continue
        for r in range(9):
            s = 0.0
            for c in range(dims[i]):
                s += Q[r, c] * z[offsets[i] + c]
            D[i, r // 3, r % 3] = s
    Fp = _expm_sym(D[0]) @ Fp_n
    E = _expm_sym(D[1] - D[0])
    chip = E @ chip_n
    Gp = np.zeros((3, 3, 3))
    for b in range(3):
        for J in range(3):
            for K in range(3):
                s = 0.0
                for c in range(3):
                    s += E[b, c] * Gp_n[c, J, K]
                for C in range(3):
                    for a in range(3):
                        s += D[2 + C, b, a] * chip[a, J] * Fp[C, K]
                Gp[b, J, K] = s
    return Fp, chip, Gp, D


@numba.njit(cache=True)
def _level_residual(R, o, d, mode, t, zl, dl, cone, eq_old, Q):
    """One level's rows of the residual (the equations of micromorphic_return)."""
    A, B, k0, H = cone[0], cone[1], cone[2], cone[3]
    p, dev, tau = _invariants(t)
    k = k0 + H * (eq_old + dl)
    if mode == 1:                                   # on the cone: D - dl n = 0, f = 0
        n = dev / (2.0 * tau) + B / 3.0 * _VEC_I
        for c in range(d):
            s = 0.0
            for r in range(9):
                s += Q[r, c] * n[r]
            R[o + c] = zl[c] - dl * s
        R[o + d] = tau + A * p - k
        return
    for c in range(1, d):                           # at the apex: dev t = 0, A p = k
        s = 0.0
        for r in range(9):
            s += Q[r, c] * dev[r]
        R[o + c] = s
    tr = math.sqrt(3.0) * zl[0]
    R[o] = tr - B * dl if (A * B > 0.0 or H > 0.0) else dl - tr
    R[o + d] = A * p - k


@numba.njit(cache=True)
def _evaluate(z, modes, dims, offsets, C, Psi, Gam, Fp_n, chip_n, Gp_n, eq_old, K, cones,
              Q, SYM):
    """Residual (nz,), level stresses (45,), increments and the state of unknowns z."""
    Fp, chip, Gp, D = _advance(z, modes, dims, offsets, Fp_n, chip_n, Gp_n, Q)
    Ce, Psie, Ge, _, _, _ = _elastic_measures(C, Psi, Gam, Fp, chip, Gp)
    _, psiE, T, H = _partials(Ce, Psie, Ge, K)
    ty = _level_vector(Ce, Psie, Ge, psiE, T, H)
    R = np.zeros(z.size)
    for i in range(5):
        if modes[i] != 0:
            o, d = offsets[i], dims[i]
            _level_residual(R, o, d, modes[i], _level_stress(ty, i, SYM[i]), z[o: o + d],
                            z[o + d], cones[i], eq_old[i], Q)
    return R, ty, D, Fp, chip, Gp


@numba.njit(cache=True)
def _merit(R, modes, dims, offsets, moduli):
    """|R| in stress units: the rows of increments (and the apex's volumetric row) times the
    level's shear modulus, the apex's deviatoric rows and the yield rows as they are."""
    m = 0.0
    for i in range(5):
        if modes[i] == 0:
            continue
        o, d = offsets[i], dims[i]
        for c in range(d):
            w = moduli[i, 0] if (modes[i] == 1 or c == 0) else 1.0
            m += (w * R[o + c]) ** 2
        m += R[o + d] ** 2
    return math.sqrt(m)


@numba.njit(cache=True)
def _newton(z, modes, dims, offsets, C, Psi, Gam, Fp_n, chip_n, Gp_n, eq_old, K, cones, moduli,
            Q, SYM, scale, zfloor):
    """Newton with a central-difference Jacobian and backtracking; (converged, z).
    ``zfloor`` (5,): each level's least size of unknowns for the difference steps (a level
    that joins the set starts from zero increments)."""
    nz = z.size
    R = _evaluate(z, modes, dims, offsets, C, Psi, Gam, Fp_n, chip_n, Gp_n, eq_old, K, cones,
                  Q, SYM)[0]
    merit = _merit(R, modes, dims, offsets, moduli)
    # accepted residual: 1e-9 of the stresses, or the round-off floor of stresses computed
    # from C - I at tiny strains (1e-13 of the largest modulus)
    accept = max(1e-9 * scale, 1e-13 * np.max(moduli))
    zs = np.full(nz, 1e-300)                  # each level's size of unknowns: its FD steps
    for _ in range(60):
        if not np.isfinite(merit):
            return False, z
        if merit <= 1e-12 * scale:
            return True, z
        for i in range(5):
            if modes[i] != 0:
                o, d = offsets[i], dims[i]
                zs[o: o + d + 1] = max(zs[o], zfloor[i], np.max(np.abs(z[o: o + d + 1])))
        J = np.empty((nz, nz))
        for j in range(nz):
            h = 1e-7 * max(abs(z[j]), zs[j])
            zp, zm = z.copy(), z.copy()
            zp[j] += h
            zm[j] -= h
            Rp = _evaluate(zp, modes, dims, offsets, C, Psi, Gam, Fp_n, chip_n, Gp_n, eq_old,
                           K, cones, Q, SYM)[0]
            Rm = _evaluate(zm, modes, dims, offsets, C, Psi, Gam, Fp_n, chip_n, Gp_n, eq_old,
                           K, cones, Q, SYM)[0]
            J[:, j] = (Rp - Rm) / (2.0 * h)
        if not np.all(np.isfinite(J)):
            return False, z
        dz = _solve(J, -R.reshape(nz, 1))[:, 0]     # NaN (no exception) where J is singular
        alpha, decreased = 1.0, False
        for _half in range(30):
            zt = z + alpha * dz
            Rt = _evaluate(zt, modes, dims, offsets, C, Psi, Gam, Fp_n, chip_n, Gp_n, eq_old,
                           K, cones, Q, SYM)[0]
            mt = _merit(Rt, modes, dims, offsets, moduli)
            if np.isfinite(mt) and mt <= (1.0 - 1e-4 * alpha) * merit:
                decreased = True
                break
            alpha *= 0.5
        if not decreased:
            return merit <= accept, z
        z, R, merit = zt, Rt, mt
    return merit <= accept, z


@numba.njit(cache=True)
def _reference_stresses(C, Psi, Gam, Fp, chip, Gp, K):
    """``(S, Sigma, M, psi, T_ref)`` in the reference configuration at a plastic state
    (module docstring)."""
    Ce, Psie, Ge, Z, Fpi, chipi = _elastic_measures(C, Psi, Gam, Fp, chip, Gp)
    x, psiE, T, H = _partials(Ce, Psie, Ge, K)
    Teff = T.copy()
    for i in range(3):
        for d in range(3):
            for a in range(3):
                for c in range(3):
                    Teff[i, d] -= H[i, a, c] * Z[d, a, c]
    psiE_ref = Fpi @ psiE @ Fpi.T
    T_ref = Fpi @ Teff @ chipi.T
    M = np.zeros((3, 3, 3))
    for a in range(3):
        for b in range(3):
            for c in range(3):
                h = H[a, b, c]
                for i in range(3):
                    for j in range(3):
                        w = Fpi[i, a] * chipi[j, b] * h
                        for k in range(3):
                            M[i, j, k] += w * Fpi[k, c]
    Ci = _inv3(C)
    extra = Ci @ Psi @ T_ref.T
    CiG = np.zeros((3, 3, 3))
    for i in range(3):
        for q in range(3):
            for r in range(3):
                for s in range(3):
                    CiG[i, q, r] += Ci[i, s] * Gam[s, q, r]
    for i in range(3):
        for j in range(3):
            for q in range(3):
                for r in range(3):
                    extra[i, j] += CiG[i, q, r] * M[j, q, r]
    S = psiE_ref + extra
    Sigma = psiE_ref + extra + extra.T
    return S, Sigma, M, 0.5 * np.dot(x, K @ x), T_ref


@numba.njit(cache=True)
def _start(ty, cones, has_cone, eq_old, moduli, scale, Q, SYM, modes, a_cone, l_cone, a_apex,
           l_apex, flags):
    """The trial yield values, the levels that yield and their predicted unknowns."""
    for i in range(5):
        flags[i] = 0.0
        if not has_cone[i]:
            continue
        cone = cones[i].copy()
        cone[2] += cone[3] * eq_old[i]
        p, _, tau = _invariants(_level_stress(ty, i, SYM[i]))
        f = tau + cone[0] * p - cone[2]
        flags[i] = 1.0 if f > 0.0 else 0.0
        if f > 1e-12 * scale:
            l_cone[i], l_apex[i], apex = _predict(ty, i, cone, moduli[i, 0], moduli[i, 1],
                                                  SYM[i], Q, _VEC_I, a_cone[i], a_apex[i])
            modes[i] = 2 if apex else 1


@numba.njit(cache=True)
def _point(C, Psi, Gam, Fp_n, chip_n, Gp_n, eq_old, K, cones, has_cone, moduli, Q, SYM,
           Fp_out, chip_out, Gp_out, eq_out, flags, f_out, modes_out, z_out, zfloor):
    """One point: the return (module docstring). Writes the state, the trial flags and the
    final yield values; returns ``(passes, dissipation)``, passes -1 if no active set
    converged (the outputs then hold the trial state)."""
    dims = np.empty(5, dtype=np.int64)
    for i in range(5):
        dims[i] = 6 if SYM[i] else 9
    modes = np.zeros(5, dtype=np.int64)
    offsets = np.zeros(5, dtype=np.int64)
    ty = _evaluate(np.zeros(0), modes, dims, offsets, C, Psi, Gam, Fp_n, chip_n, Gp_n, eq_old,
                   K, cones, Q, SYM)[1]
    scale = 1e-300
    for r in range(45):
        scale = max(scale, abs(ty[r]))
    for i in range(5):                         # a level's strains: its stresses / its modulus
        G = moduli[i, 0] if moduli[i, 0] > 0.0 else 1.0
        zfloor[i] = max(np.max(np.abs(ty[9 * i: 9 * i + 9])) / G, 1e-300)
    a_cone, a_apex = np.zeros((5, 9)), np.zeros((5, 9))
    l_cone, l_apex = np.zeros(5), np.zeros(5)
    _start(ty, cones, has_cone, eq_old, moduli, scale, Q, SYM, modes, a_cone, l_cone, a_apex,
           l_apex, flags)
    apex_tries = np.zeros(5, dtype=np.int64)
    for i in range(5):
        apex_tries[i] = modes[i] == 2
    Fp_out[:] = Fp_n
    chip_out[:] = chip_n
    Gp_out[:] = Gp_n
    eq_out[:] = eq_old
    for passes in range(1, 31):
        z = np.zeros(_offsets(modes, dims, offsets))
        for i in range(5):
            o, d = offsets[i], dims[i]
            if modes[i] == 1:
                z[o: o + d] = a_cone[i, :d]
                z[o + d] = l_cone[i]
            elif modes[i] == 2:
                z[o: o + d] = a_apex[i, :d]
                z[o + d] = l_apex[i]
        ok, z = _newton(z, modes, dims, offsets, C, Psi, Gam, Fp_n, chip_n, Gp_n, eq_old, K,
                        cones, moduli, Q, SYM, scale, zfloor)
        _, ty, D, Fp, chip, Gp = _evaluate(z, modes, dims, offsets, C, Psi, Gam, Fp_n, chip_n,
                                           Gp_n, eq_old, K, cones, Q, SYM)
        if not ok:
            if not _after_failure(modes, z, offsets, dims, ty, apex_tries, SYM):
                return -1, 0.0
            continue
        _warm_starts(modes, z, offsets, dims, a_cone, l_cone, a_apex, l_apex)
        before = modes.copy()
        Dflat = D.reshape(45)
        if _revise(modes, z, offsets, dims, Dflat, np.zeros(45), ty, cones, has_cone, eq_old,
                   scale, _PDEV, SYM):
            for i in range(5):
                if before[i] == 2 and modes[i] == 1:
                    a_cone[i, 0] = a_apex[i, 0]
                    a_cone[i, 1:] = 0.99 * a_apex[i, 1:]
                    dev_dp = _PDEV @ Dflat[9 * i: 9 * i + 9]
                    l_cone[i] = math.sqrt(2.0 * np.dot(dev_dp, dev_dp))
            continue
        Fp_out[:] = Fp
        chip_out[:] = chip
        Gp_out[:] = Gp
        modes_out[:] = modes
        z_out[: z.size] = z
        dissipation = 0.0
        for i in range(5):
            t = _level_stress(ty, i, SYM[i])
            dissipation += np.dot(t, Dflat[9 * i: 9 * i + 9])
            if modes[i] != 0:
                eq_out[i] = eq_old[i] + z[offsets[i] + dims[i]]
            p, _, tau = _invariants(t)
            f_out[i] = tau + cones[i, 0] * p - (cones[i, 2] + cones[i, 3] * eq_out[i])
            if modes[i] == 2:
                dev_dp = _PDEV @ Dflat[9 * i: 9 * i + 9]
                eq_out[i] += math.sqrt(2.0 * np.dot(dev_dp, dev_dp))
        return passes, dissipation
    return -1, 0.0


@numba.njit(cache=True)
def _fields_measures(x):
    """``(F, C, Psi, Gamma)`` of the field derivatives ``x`` (45: grad u, phi, grad phi)."""
    F, chi, gc = np.eye(3), np.eye(3), np.empty((3, 3, 3))
    for r in range(9):
        F[r // 3, r % 3] += x[r]
        chi[r // 3, r % 3] += x[9 + r]
    for r in range(27):
        gc[r // 9, (r // 3) % 3, r % 3] = x[18 + r]
    Gam = np.zeros((3, 3, 3))
    for I in range(3):
        for J in range(3):
            for K in range(3):
                for i in range(3):
                    Gam[I, J, K] += F[i, I] * gc[i, J, K]
    return F, F.T @ F, F.T @ chi, Gam


@numba.njit(cache=True)
def _nominal_at(x, z, modes, dims, offsets, Fp_n, chip_n, Gp_n, K, Q):
    """The nominal stresses ``[P, Q, R]`` (45) of fields ``x`` and unknowns ``z``."""
    F, C, Psi, Gam = _fields_measures(x)
    Fp, chip, Gp, _ = _advance(z, modes, dims, offsets, Fp_n, chip_n, Gp_n, Q)
    S, _, M, _, T_ref = _reference_stresses(C, Psi, Gam, Fp, chip, Gp, K)
    y = np.zeros(45)
    P, Qn = F @ S, F @ T_ref
    for r in range(9):
        y[r], y[9 + r] = P[r // 3, r % 3], Qn[r // 3, r % 3]
    for i in range(3):
        for J in range(3):
            for L in range(3):
                for I in range(3):
                    y[18 + 9 * i + 3 * J + L] += F[i, I] * M[I, J, L]
    return y


@numba.njit(cache=True)
def _tangent(x, z, modes, dims, offsets, Fp_n, chip_n, Gp_n, eq_old, K, cones, Q, SYM, zfloor):
    """The consistent tangent ``d[P, Q, R] / dx`` (45 x 45) at the converged unknowns z:
    ``Y_x - Y_z J^-1 R_x`` (implicit function theorem; every partial by central
    differences, steps 1e-7 of each block's size, at least 1e-8)."""
    nz = z.size
    xs = np.empty(45)
    for j in range(45):
        # 1e-7 of the block's size, at least 1e-8: F = I + grad u rounds smaller steps away
        lo, hi = (0, 18) if j < 18 else (18, 45)
        xs[j] = max(1e-7 * np.max(np.abs(x[lo:hi])), 1e-8)
    Yx, Rx = np.empty((45, 45)), np.empty((nz, 45))
    for j in range(45):
        xp, xm = x.copy(), x.copy()
        xp[j] += xs[j]
        xm[j] -= xs[j]
        Yx[:, j] = (_nominal_at(xp, z, modes, dims, offsets, Fp_n, chip_n, Gp_n, K, Q)
                    - _nominal_at(xm, z, modes, dims, offsets, Fp_n, chip_n, Gp_n, K, Q)) \
            / (2.0 * xs[j])
        if nz > 0:
            _, Cp, Pp, Gp_ = _fields_measures(xp)
            _, Cm, Pm, Gm = _fields_measures(xm)
            Rx[:, j] = (_evaluate(z, modes, dims, offsets, Cp, Pp, Gp_, Fp_n, chip_n, Gp_n,
                                  eq_old, K, cones, Q, SYM)[0]
                        - _evaluate(z, modes, dims, offsets, Cm, Pm, Gm, Fp_n, chip_n, Gp_n,
                                    eq_old, K, cones, Q, SYM)[0]) / (2.0 * xs[j])
    if nz == 0:
        return Yx
    _, C, Psi, Gam = _fields_measures(x)
    Jz, Yz = np.empty((nz, nz)), np.empty((45, nz))
    steps = np.empty(nz)
    for i in range(5):
        if modes[i] != 0:
            o, d = offsets[i], dims[i]
            steps[o: o + d + 1] = 1e-7 * max(np.max(np.abs(z[o: o + d + 1])), zfloor[i])
    for j in range(nz):
        h = steps[j]
        zp, zm = z.copy(), z.copy()
        zp[j] += h
        zm[j] -= h
        Jz[:, j] = (_evaluate(zp, modes, dims, offsets, C, Psi, Gam, Fp_n, chip_n, Gp_n, eq_old,
                              K, cones, Q, SYM)[0]
                    - _evaluate(zm, modes, dims, offsets, C, Psi, Gam, Fp_n, chip_n, Gp_n,
                                eq_old, K, cones, Q, SYM)[0]) / (2.0 * h)
        Yz[:, j] = (_nominal_at(x, zp, modes, dims, offsets, Fp_n, chip_n, Gp_n, K, Q)
                    - _nominal_at(x, zm, modes, dims, offsets, Fp_n, chip_n, Gp_n, K, Q)) \
            / (2.0 * h)
    return Yx - Yz @ _solve(Jz, Rx)


@numba.njit(cache=True)
def _all(x, Fp_n, chip_n, Gp_n, eq_n, K, cones, has_cone, moduli, Q, SYM, Fp, chip, Gp, eq,
         flags, f, passes, dissipation, S, Sigma, M, psi, nominal, tangent, want_tangent):
    dims = np.empty(5, dtype=np.int64)
    for i in range(5):
        dims[i] = 6 if SYM[i] else 9
    for n in range(x.shape[0]):
        _, C, Psi, Gam = _fields_measures(x[n])
        modes, z_all, zfloor = np.zeros(5, dtype=np.int64), np.zeros(50), np.empty(5)
        passes[n], dissipation[n] = _point(
            C, Psi, Gam, Fp_n[n], chip_n[n], Gp_n[n], eq_n[n], K, cones, has_cone, moduli, Q,
            SYM, Fp[n], chip[n], Gp[n], eq[n], flags[n], f[n], modes, z_all, zfloor)
        S[n], Sigma[n], M[n], psi[n], _ = _reference_stresses(C, Psi, Gam, Fp[n], chip[n],
                                                              Gp[n], K)
        if passes[n] < 0:
            modes[:] = 0
        offsets = np.zeros(5, dtype=np.int64)
        z = z_all[:_offsets(modes, dims, offsets)].copy()
        nominal[n] = _nominal_at(x[n], z, modes, dims, offsets, Fp_n[n], chip_n[n], Gp_n[n], K, Q)
        if want_tangent:
            tangent[n] = _tangent(x[n], z, modes, dims, offsets, Fp_n[n], chip_n[n], Gp_n[n],
                                  eq_n[n], K, cones, Q, SYM, zfloor)


# ---- the numpy interface ---------------------------------------------------------------

def _reference_measures(grad_u, chi, grad_chi):
    """``(C, Psi, Gamma)`` flattened to n points, and the points' shape."""
    grad_u = np.asarray(grad_u, dtype=float)
    shape = grad_u.shape[:-2]
    F = np.eye(3) + grad_u.reshape(-1, 3, 3)
    chi = np.asarray(chi, dtype=float).reshape(-1, 3, 3)
    C = np.einsum("niI,niJ->nIJ", F, F)
    Psi = np.einsum("niI,niJ->nIJ", F, chi)
    Gam = np.einsum("niI,niJK->nIJK", F, np.asarray(grad_chi, dtype=float).reshape(-1, 3, 3, 3))
    return C, Psi, Gam, shape


def _flat_state(state, n):
    return tuple(np.ascontiguousarray(np.broadcast_to(state[k], (n, *tail)), dtype=float)
                 for k, tail in (("Fp", (3, 3)), ("chip", (3, 3)), ("Gp", (3, 3, 3)),
                                 ("eq", (LEVEL_COUNT,))))


def finite_return(grad_u, chi, grad_chi, state, material, tables: KernelTables | None = None,
                  tangent: bool = False):
    """The return at material points (3D): stresses and the updated plastic state.

    Args:
        grad_u: ``grad_u[..., i, J] = u_i,J`` (reference gradient; ``F = I + grad_u``),
            shape (..., 3, 3).
        chi: the micro-deformation ``chi[..., i, J]``, shape (..., 3, 3).
        grad_chi: ``grad_chi[..., i, J, K] = chi_iJ,K``, shape (..., 3, 3, 3).
        state: the committed plastic state (:func:`initial_state`): ``Fp``, ``chip``
            (..., 3, 3), ``Gp`` (..., 3, 3, 3), ``eq`` (..., 5: macro, micro, slices 0-2).
        material: a :class:`~granfe.models.micromorphic_drucker_prager.MicromorphicDruckerPragerMaterial`
            (any moduli; a level without a cone stays elastic).
        tables: :func:`kernel_tables` of the material (computed when None).
        tangent: also the consistent tangent (central differences of the return's
            equations, ~0.5 k evaluations of them a yielding point).

    Returns:
        ``(S, Sigma, M, new_state, info)``: the reference stresses (module docstring;
        [Pa], [Pa], [Pa m]), the updated state (same keys) and ``info``: ``yielding``
        (..., 5: the trial stress was outside the level's cone), ``f`` (..., 5: the
        levels' yield values at the end of the step, [Pa] / [Pa m]; 0 for an elastic
        level; at the strength of the step's equations: at the apex the committed ``eq``
        also adds ``sqrt 2 |dev D|``, as the small-strain model's closed form, which leaves
        the point inside its cone), ``dissipation`` (...: ``sum_i t_i : D_i`` [J/m^3]), ``psi`` (...: the stored
        energy [J/m^3]), ``passes`` (...: active-set passes, -1 where the return failed and
        the outputs hold the trial state), ``nominal`` (..., 45: ``[P, Q, R]`` = ``F S``,
        ``F T^ref``, ``F_iI M_IJK``, the integrands of the residual against ``[grad du,
        dphi, grad dphi]``, row-major) and with ``tangent`` ``tangent`` (..., 45, 45: the
        derivative of ``nominal`` in ``[grad u, phi, grad phi]`` at the committed state).
    """
    if not isinstance(material, MicromorphicDruckerPragerMaterial):
        raise TypeError("finite_return: material must be a MicromorphicDruckerPragerMaterial")
    tab = tables or kernel_tables(material)
    grad_u = np.asarray(grad_u, dtype=float)
    shape = grad_u.shape[:-2]
    x = np.concatenate([grad_u.reshape(-1, 9),
                        (np.asarray(chi, dtype=float) - np.eye(3)).reshape(-1, 9),
                        np.asarray(grad_chi, dtype=float).reshape(-1, 27)], axis=1)
    n = x.shape[0]
    Fp_n, chip_n, Gp_n, eq_n = _flat_state(state, n)
    Fp, chip, Gp, eq = np.empty_like(Fp_n), np.empty_like(chip_n), np.empty_like(Gp_n), \
        np.empty_like(eq_n)
    flags, f = np.empty((n, LEVEL_COUNT)), np.zeros((n, LEVEL_COUNT))
    passes, dissipation, psi = np.empty(n, dtype=np.int64), np.empty(n), np.empty(n)
    S, Sigma, M = np.empty((n, 3, 3)), np.empty((n, 3, 3)), np.empty((n, 3, 3, 3))
    nominal, C = np.empty((n, 45)), np.empty((n if tangent else 1, 45, 45))
    _all(x, Fp_n, chip_n, Gp_n, eq_n, tab.K, tab.cones, tab.has_cone, tab.moduli, _Q,
         _SYMMETRIC, Fp, chip, Gp, eq, flags, f, passes, dissipation, S, Sigma, M, psi, nominal,
         C, bool(tangent))

    def back(a):
        return a.reshape(tuple(shape) + a.shape[1:])

    new_state = {"Fp": back(Fp), "chip": back(chip), "Gp": back(Gp), "eq": back(eq)}
    info = {"yielding": back(flags), "f": back(f), "dissipation": back(dissipation),
            "psi": back(psi), "passes": back(passes), "nominal": back(nominal)}
    if tangent:
        info["tangent"] = back(C)
    return back(S), back(Sigma), back(M), new_state, info


def elastic_energy(grad_u, chi, grad_chi, state, material, tables: KernelTables | None = None):
    """The stored energy psi [J/m^3] at a fixed plastic state (arguments as
    :func:`finite_return`)."""
    tab = tables or kernel_tables(material)
    return _at_state(grad_u, chi, grad_chi, state, tab)[3]


def level_stresses(grad_u, chi, grad_chi, state, material, tables: KernelTables | None = None):
    """The five levels' yield stresses ``t_i`` (..., 5, 3, 3) at a fixed plastic state: the
    conjugates of the plastic increments (module docstring; the macro and micro ones
    symmetric)."""
    tab = tables or kernel_tables(material)
    C, Psi, Gam, shape = _reference_measures(grad_u, chi, grad_chi)
    Fp, chip, Gp, _ = _flat_state(state, C.shape[0])
    out = np.empty((C.shape[0], LEVEL_COUNT, 3, 3))
    for n in range(C.shape[0]):
        Ce, Psie, Ge, _, _, _ = _elastic_measures(C[n], Psi[n], Gam[n], Fp[n], chip[n], Gp[n])
        _, psiE, T, H = _partials(Ce, Psie, Ge, tab.K)
        ty = _level_vector(Ce, Psie, Ge, psiE, T, H)
        for i in range(LEVEL_COUNT):
            out[n, i] = _level_stress(ty, i, _SYMMETRIC[i]).reshape(3, 3)
    return out.reshape(tuple(shape) + (LEVEL_COUNT, 3, 3))


def _at_state(grad_u, chi, grad_chi, state, tab):
    C, Psi, Gam, shape = _reference_measures(grad_u, chi, grad_chi)
    Fp, chip, Gp, _ = _flat_state(state, C.shape[0])
    outs = [_reference_stresses(C[n], Psi[n], Gam[n], Fp[n], chip[n], Gp[n], tab.K)[:4]
            for n in range(C.shape[0])]
    return tuple(np.array([o[k] for o in outs]).reshape(tuple(shape) + np.shape(outs[0][k]))
                 for k in range(4))
