"""The return mapping of three-level micromorphic Drucker-Prager plasticity for any moduli, at
material points (numpy / numba; no mesh).

With coupled moduli (``D != 0``: tau, sigma; or the taus other than tau7) the stress of one
level depends on the plastic parts of the others, so the levels return together: Newton on
the plastic increments and multipliers of every yielding level at once, the consistent
tangent from the converged Jacobian. With decoupled moduli it is the closed-form radial
return of :func:`~granfe.models.micromorphic_drucker_prager.cone_return` on each level (the
tests hold the two to round-off).

Measures and stresses in one vector of 45 components (3D, row-major 3 x 3 blocks; plane
strain embeds its in-plane components, the out-of-plane ones zero)::

    x = [eps_ij (9), E_ij (9), G_klM for M = 0, 1, 2 (9 each, [k, l])],
    y = dW/dx = [S_ij, T_ij, m_klM],     W = x . K x / 2,

``K`` (45 x 45, symmetric) the Hessian of the energy of
:mod:`granfe.models.micromorphic` (:func:`stiffness`). Level ``i`` owns block ``i`` (macro
``eps`` / ``S``; micro ``E`` / ``T``, yielding in ``sym T``; slice ``M`` of the higher-order
measure, level ``2 + M``). Each level's plastic increment lives in a subspace of its block
(symmetric for the macro and micro levels, all 3 x 3 for a slice), written in an orthonormal
basis ``Q`` whose first vector is ``I / sqrt 3`` and the others deviatoric.

The equations of a yielding level (``t`` its stress: ``S``, ``sym T`` or ``m_..M``;
``tau = sqrt(J2)``, ``p = tr t / 3``; committed equivalent plastic strain ``e``):

* on the cone, unknowns ``a`` (the increment ``Q a``) and ``dl``::

      a - dl Q^T n(t) = 0,   n = dev t / (2 tau) + B I / 3,
      tau + A p - (k0 + H (e + dl)) = 0,            e += dl;

* at the apex (where the cone's return would cross it), unknowns ``a`` and ``dl``::

      Q^T dev t = 0 (all rows but the trace row),
      tr(Q a) - B dl = 0   (or dl - tr(Q a) = 0 when B = H = 0),
      A p - (k0 + H (e + dl)) = 0,                   e += dl + sqrt(2) |dev Q a|,

  the closed form's apex return written for coupled moduli.

The stress ``y = K (x - x_p)``. Which levels yield, and which of them sit at the apex, is
found by an active-set loop: levels whose trial yield value is positive beyond round-off,
each on its cone or at its apex as the decoupled radial return of its own diagonal moduli
predicts (and starting from that return: with decoupled moduli it is the answer); a level
whose multiplier comes out negative leaves the set, a level left out that the converged
stress violates joins it, an apex whose flow leaves the plastic potential's normal cone
there goes back to the cone (started next to the apex), a level whose cone return fails
(its deviator collapsing) goes to the apex. Newton backtracks on the residual and stops at
its round-off floor (~1e-9 of the stress with all five levels coupled and yielding).
Measured on random states of 1e-4 to 1e-2 strain in all 45 components, all levels
yielding, coupled moduli: 1 point in 8000 finds no set (it keeps its trial state and the
caller fails the solve, which restores the last converged state).
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["NX", "LEVEL_COUNT", "stiffness", "level_moduli", "point_return"]

NX = 45
LEVEL_COUNT = 5
_SYMMETRIC = np.array([True, True, False, False, False])
_VEC_I = np.eye(3).ravel()


def _basis() -> np.ndarray:
    """Orthonormal basis (9 x 9, columns) of 3 x 3 matrices (row-major): I / sqrt 3, the two
    deviatoric diagonals, the three symmetric off-diagonals (the first six span the
    symmetric matrices), the three skew ones."""
    Q = np.zeros((9, 9))
    Q[:, 0] = _VEC_I / math.sqrt(3.0)
    Q[:, 1] = np.diag([1.0, -1.0, 0.0]).ravel() / math.sqrt(2.0)
    Q[:, 2] = np.diag([1.0, 1.0, -2.0]).ravel() / math.sqrt(6.0)
    for c, (i, j) in enumerate(((1, 2), (0, 2), (0, 1))):
        s, k = np.zeros((3, 3)), np.zeros((3, 3))
        s[i, j] = s[j, i] = k[i, j] = 1.0 / math.sqrt(2.0)
        k[j, i] = -1.0 / math.sqrt(2.0)
        Q[:, 3 + c], Q[:, 6 + c] = s.ravel(), k.ravel()
    return Q


_Q = _basis()
_PSYM = _Q[:, :6] @ _Q[:, :6].T          # the symmetric part of a 3 x 3 (row-major)
_PDEV = np.eye(9) - np.outer(_VEC_I, _VEC_I) / 3.0
# each level's projection onto its yield stress: the symmetric part, or all of the block
_PROJ = np.stack([_PSYM if sym else np.eye(9) for sym in _SYMMETRIC])


def _stresses_of(x: np.ndarray, material) -> np.ndarray:
    """The stresses y = dW/dx (45,) for measures x (45,), the energy of granfe.models.micromorphic with
    the macro strain's own symmetry kept (so that K is symmetric on all 45 components)."""
    from granfe.models.micromorphic import _np_higher_order

    c = material
    eye = np.eye(3)
    eps, E = x[:9].reshape(3, 3), x[9:18].reshape(3, 3)
    G = np.stack([x[18 + 9 * M: 27 + 9 * M].reshape(3, 3) for M in range(3)], axis=-1)
    tr_e, tr_E = np.trace(eps), np.trace(E)
    S = c.lam * tr_e * eye + c.mu * (eps + eps.T) + c.tau * tr_E * eye + c.sigma * (E + E.T)
    T = ((c.eta - c.tau) * tr_E * eye + c.kappa * E + c.nu * E.T - c.sigma * (E + E.T)
         + c.tau * tr_e * eye + c.sigma * (eps + eps.T))
    m = _np_higher_order(G, c.taus, eye)
    return np.concatenate([S.ravel(), T.ravel()] + [m[:, :, M].ravel() for M in range(3)])


def stiffness(material) -> np.ndarray:
    """K (45 x 45) [Pa; Pa m^2 on the higher-order block]: ``y = K x`` (module docstring)."""
    K = np.column_stack([_stresses_of(e, material) for e in np.eye(NX)])
    return 0.5 * (K + K.T)


def level_moduli(K: np.ndarray) -> np.ndarray:
    """(5, 2): each level's shear and bulk moduli ``(G, K)`` from its diagonal block (the
    decoupled radial return's; the apex predictor's): ``G = q . K q / 2`` averaged over its
    deviatoric basis vectors q, ``K = (I / sqrt 3) . K (I / sqrt 3) / 3``."""
    out = np.zeros((LEVEL_COUNT, 2))
    for i in range(LEVEL_COUNT):
        Kb = K[9 * i: 9 * i + 9, 9 * i: 9 * i + 9]
        d = 6 if _SYMMETRIC[i] else 9
        Qd = _Q[:, 1:d]
        out[i, 0] = np.trace(Qd.T @ Kb @ Qd) / (2 * (d - 1))
        out[i, 1] = _Q[:, 0] @ Kb @ _Q[:, 0] / 3
    return out


# ---- the kernel ------------------------------------------------------------------------

@numba.njit(cache=True)
def _level_stress(y, i, sym):
    """The yield stress t (9,) of level i: its block of y, symmetrised for the macro and
    micro levels."""
    t = np.empty(9)
    for r in range(3):
        for c in range(3):
            a, b = y[9 * i + 3 * r + c], y[9 * i + 3 * c + r]
            t[3 * r + c] = 0.5 * (a + b) if sym else a
    return t


@numba.njit(cache=True)
def _invariants(t):
    p = (t[0] + t[4] + t[8]) / 3.0
    dev = t.copy()
    dev[0] -= p
    dev[4] -= p
    dev[8] -= p
    tau = math.sqrt(0.5 * np.dot(dev, dev))
    return p, dev, tau


@numba.njit(cache=True)
def _system(z, x, K, xp_old, eq_old, cones, modes, dims, offsets, Q, PROJ, PDEV, VEC_I, SYM):
    """Residual R (nz,), its Jacobian J (nz, nz), dR/dy at fixed z (nz, 45), dy/dz (45, nz),
    the stress y and the plastic measures xp of unknowns z."""
    nz = z.size
    xp = xp_old.copy()
    for i in range(5):
        if modes[i] == 0:
            continue
        o, d = offsets[i], dims[i]
        for r in range(9):
            s = 0.0
            for c in range(d):
                s += Q[r, c] * z[o + c]
            xp[9 * i + r] += s
    y = K @ (x - xp)
    R = np.zeros(nz)
    Ry = np.zeros((nz, 45))
    Rz = np.zeros((nz, nz))
    Yz = np.zeros((45, nz))
    for i in range(5):
        if modes[i] == 0:
            continue
        o, d = offsets[i], dims[i]
        lam = o + d                                   # the multiplier's index
        A, B, k0, H = cones[i, 0], cones[i, 1], cones[i, 2], cones[i, 3]
        P = PROJ[i]
        QdT = np.ascontiguousarray(Q[:, :d].T)
        t = _level_stress(y, i, SYM[i])
        p, dev, tau = _invariants(t)
        for c in range(d):
            for r in range(45):
                s = 0.0
                for q in range(9):
                    s -= K[r, 9 * i + q] * Q[q, c]
                Yz[r, o + c] = s
        k = k0 + H * (eq_old[i] + z[lam])
        if modes[i] == 1:                             # on the cone
            n = dev / (2.0 * tau) + B / 3.0 * VEC_I
            Dn = PDEV / (2.0 * tau) - np.outer(dev, dev) / (4.0 * tau**3)
            dRa_dt = -z[lam] * (QdT @ Dn)      # (d, 9)
            dRa_dy = dRa_dt @ P
            Qn = QdT @ n
            for c in range(d):
                R[o + c] = z[o + c] - z[lam] * Qn[c]
                Rz[o + c, o + c] = 1.0
                Rz[o + c, lam] = -Qn[c]
                for q in range(9):
                    Ry[o + c, 9 * i + q] = dRa_dy[c, q]
            R[lam] = tau + A * p - k
            df = (dev / (2.0 * tau) + A / 3.0 * VEC_I) @ P
            for q in range(9):
                Ry[lam, 9 * i + q] = df[q]
            Rz[lam, lam] = -H
        else:                                         # at the apex
            dRd_dy = QdT @ PDEV @ P
            Qd = QdT @ dev
            for c in range(1, d):
                R[o + c] = Qd[c]
                for q in range(9):
                    Ry[o + c, 9 * i + q] = dRd_dy[c, q]
            tr = math.sqrt(3.0) * z[o]                # tr(Q a): the other columns are traceless
            if A * B > 0.0 or H > 0.0:           # the closed form's K A B + H > 0
                R[o] = tr - B * z[lam]
                Rz[o, o] = math.sqrt(3.0)
                Rz[o, lam] = -B
            else:
                R[o] = z[lam] - tr
                Rz[o, o] = -math.sqrt(3.0)
                Rz[o, lam] = 1.0
            R[lam] = A * p - k
            df = (A / 3.0 * VEC_I) @ P
            for q in range(9):
                Ry[lam, 9 * i + q] = df[q]
            Rz[lam, lam] = -H
    J = Ry @ Yz + Rz
    return R, J, Ry, Yz, y, xp


@numba.njit(cache=True)
def _merit(R, modes, dims, offsets, moduli):
    """|R| with the increments' rows in stress units (times the level's shear modulus)."""
    m = 0.0
    for i in range(5):
        if modes[i] == 0:
            continue
        o, d = offsets[i], dims[i]
        for c in range(d):
            m += (moduli[i, 0] * R[o + c]) ** 2
        m += R[o + d] ** 2
    return math.sqrt(m)


@numba.njit(cache=True)
def _offsets(modes, dims, offsets) -> int:
    """Each active level's first index among the unknowns (its dims[i] increments, then its
    multiplier) into ``offsets``; returns their number."""
    nz = 0
    for i in range(5):
        offsets[i] = nz
        if modes[i] != 0:
            nz += dims[i] + 1
    return nz


@numba.njit(cache=True)
def _newton(x, K, xp_old, eq_old, cones, modes, dims, a0, l0, moduli, Q, PROJ, PDEV, VEC_I, SYM,
            scale, tol, max_it):
    """Newton, from the levels' predicted unknowns (a0, l0), on the unknowns of the levels in
    ``modes``, with backtracking on the residual (a full step may jump a cone's deviator
    through zero); (converged, z, offsets, J, Ry, Yz, y, xp)."""
    offsets = np.zeros(5, dtype=np.int64)
    nz = _offsets(modes, dims, offsets)
    z = np.zeros(nz)
    for i in range(5):
        if modes[i] != 0:
            z[offsets[i]: offsets[i] + dims[i]] = a0[i, : dims[i]]
            z[offsets[i] + dims[i]] = l0[i]
    R, J, Ry, Yz, y, xp = _system(z, x, K, xp_old, eq_old, cones, modes, dims, offsets,
                                  Q, PROJ, PDEV, VEC_I, SYM)
    merit = _merit(R, modes, dims, offsets, moduli)
    for _ in range(max_it):
        if not np.isfinite(merit):
            return False, z, offsets, J, Ry, Yz, y, xp
        if merit <= 1e-13 * scale:
            return True, z, offsets, J, Ry, Yz, y, xp
        dz = np.linalg.solve(J, -R)
        small = True
        for j in range(nz):
            if abs(dz[j]) > tol * (1.0 + abs(z[j])):
                small = False
        alpha = 1.0
        decreased = False
        for _half in range(30):
            zt = z + alpha * dz
            Rt, Jt, Ryt, Yzt, yt, xpt = _system(zt, x, K, xp_old, eq_old, cones, modes, dims,
                                                offsets, Q, PROJ, PDEV, VEC_I, SYM)
            mt = _merit(Rt, modes, dims, offsets, moduli)
            if np.isfinite(mt) and mt <= (1.0 - 1e-4 * alpha) * merit:
                decreased = True
                break
            alpha *= 0.5
        if not decreased or small:
            # at the round-off floor of the residual (the Jacobian's condition number times
            # the stresses' precision): converged if the residual is that small
            if decreased:
                z, R, J, Ry, Yz, y, xp, merit = zt, Rt, Jt, Ryt, Yzt, yt, xpt, mt
            return merit <= 1e-7 * scale, z, offsets, J, Ry, Yz, y, xp
        stalled = mt > 0.5 * merit          # Newton no longer quadratic: the floor
        z, R, J, Ry, Yz, y, xp, merit = zt, Rt, Jt, Ryt, Yzt, yt, xpt, mt
        if stalled and merit <= 1e-7 * scale:
            return True, z, offsets, J, Ry, Yz, y, xp
    return merit <= 1e-7 * scale, z, offsets, J, Ry, Yz, y, xp


@numba.njit(cache=True)
def _predict(y, i, cone, G, Kv, sym, Q, VEC_I, a_cone, a_apex):
    """The decoupled radial return of level i with its diagonal moduli (G, Kv): the
    unknowns on the cone and at the apex (a_cone, a_apex, in place) and their multipliers,
    and whether it predicts the apex."""
    A, B, k0, H = cone[0], cone[1], cone[2], cone[3]
    d = 6 if sym else 9
    p, dev, tau = _invariants(_level_stress(y, i, sym))
    f = tau + A * p - k0
    dl = f / (G + Kv * A * B + H)
    flow = dl * (dev / (2.0 * tau) + B / 3.0 * VEC_I)
    stiff = Kv * A * B + H
    if stiff > 0.0:
        dl_apex = (A * p - k0) / stiff
        p_apex = p - Kv * B * dl_apex
    else:
        dl_apex = (p - k0 / max(A, 1e-300)) / Kv
        p_apex = k0 / max(A, 1e-300)
    apex_flow = dev / (2.0 * G) + (p - p_apex) / (3.0 * Kv) * VEC_I
    for c in range(d):
        a_cone[c] = 0.0
        a_apex[c] = 0.0
        for r in range(9):
            a_cone[c] += Q[r, c] * flow[r]
            a_apex[c] += Q[r, c] * apex_flow[r]
    return dl, dl_apex, tau - G * dl < 0.0


@numba.njit(cache=True)
def _revise(modes, z, offsets, dims, xp, xp_old, y, cones, has_cone, eq_old, scale, PDEV, SYM):
    """Change the active set after a converged pass (True if changed): a cone level with a
    negative multiplier unloads; an apex whose flow leaves the plastic potential's normal
    cone there (sqrt 2 |dev dp| > dl) belongs on the cone; a level left out whose stress the
    pass put outside its cone joins."""
    changed = False
    for i in range(5):
        lam = offsets[i] + dims[i]
        if modes[i] == 1 and z[lam] < 0.0:
            modes[i] = 0
            changed = True
        elif modes[i] == 2 and (cones[i, 0] * cones[i, 1] > 0.0 or cones[i, 3] > 0.0):
            dev_dp = PDEV @ (xp[9 * i: 9 * i + 9] - xp_old[9 * i: 9 * i + 9])
            if math.sqrt(2.0 * np.dot(dev_dp, dev_dp)) > z[lam] * (1.0 + 1e-10):
                modes[i] = 1
                changed = True
    for i in range(5):
        if has_cone[i] and modes[i] == 0:
            A, k0, H = cones[i, 0], cones[i, 2], cones[i, 3]
            p, dev, tau = _invariants(_level_stress(y, i, SYM[i]))
            if tau + A * p - (k0 + H * eq_old[i]) > 1e-10 * scale:
                modes[i] = 1
                changed = True
    return changed


@numba.njit(cache=True)
def _warm_starts(modes, z, offsets, dims, a_cone, l_cone, a_apex, l_apex):
    """Keep a converged pass's unknowns as the next pass's start; a level left out starts
    from its trial state if it joins."""
    for i in range(5):
        o, d = offsets[i], dims[i]
        if modes[i] == 1:
            a_cone[i, :d], l_cone[i] = z[o: o + d], z[o + d]
        elif modes[i] == 2:
            a_apex[i, :d], l_apex[i] = z[o: o + d], z[o + d]
        else:
            a_cone[i, :] = 0.0
            l_cone[i] = 0.0


@numba.njit(cache=True)
def _after_failure(modes, z, offsets, dims, y, apex_tries, SYM):
    """Change the active set after a pass whose Newton failed (True if changed): drop the
    cone level whose multiplier went most negative (it unloads: with it in the set there
    is no solution), else send the cone level whose deviator collapsed to its apex (at most
    twice a level)."""
    drop, most = -1, 0.0
    for i in range(5):
        if modes[i] == 1 and z[offsets[i] + dims[i]] < most:
            drop, most = i, z[offsets[i] + dims[i]]
    if drop >= 0:
        modes[drop] = 0
        return True
    worst, lowest = -1, 1e300
    for i in range(5):
        if modes[i] == 1 and apex_tries[i] < 2:
            t_i = _invariants(_level_stress(y, i, SYM[i]))[2]
            if t_i < lowest:
                worst, lowest = i, t_i
    if worst < 0:
        return False
    modes[worst] = 2
    apex_tries[worst] += 1
    return True


@numba.njit(cache=True)
def _return_one(x, K, xp_old, eq_old, cones, has_cone, moduli, Q, PROJ, PDEV, VEC_I, SYM,
                y_out, C_out, xp_out, eq_out, flags_out, tangent):
    """One point (module docstring). Returns the number of active-set passes, -1 if none
    converged. ``tangent``: write the consistent tangent of a plastic point to ``C_out``
    (an elastic point's is ``K``, which the caller writes), else leave it."""
    dims = np.empty(5, dtype=np.int64)
    for i in range(5):
        dims[i] = 6 if SYM[i] else 9
    y = K @ (x - xp_old)
    scale = 1e-300
    for r in range(45):
        scale = max(scale, abs(y[r]))
    modes = np.zeros(5, dtype=np.int64)
    a_cone, a_apex = np.zeros((5, 9)), np.zeros((5, 9))
    l_cone, l_apex = np.zeros(5), np.zeros(5)
    apex_tries = np.zeros(5, dtype=np.int64)
    for i in range(5):
        flags_out[i] = 0.0
        if not has_cone[i]:
            continue
        cone = cones[i].copy()
        cone[2] += cone[3] * eq_old[i]           # the committed strength k0 + H e
        p, dev, tau = _invariants(_level_stress(y, i, SYM[i]))
        f = tau + cone[0] * p - cone[2]
        flags_out[i] = 1.0 if f > 0.0 else 0.0       # as the closed form flags it
        if f > 1e-12 * scale:                        # on the cone to round-off: elastic
            l_cone[i], l_apex[i], apex = _predict(y, i, cone, moduli[i, 0], moduli[i, 1],
                                                  SYM[i], Q, VEC_I, a_cone[i], a_apex[i])
            modes[i] = 2 if apex else 1
            apex_tries[i] = apex
    xp_out[:] = xp_old
    eq_out[:] = eq_old
    y_out[:] = y
    a0, l0 = np.zeros((5, 9)), np.zeros(5)
    for passes in range(1, 31):
        active = 0
        for i in range(5):
            active += modes[i] != 0
            if modes[i] == 2:
                a0[i], l0[i] = a_apex[i], l_apex[i]
            elif modes[i] == 1:
                a0[i], l0[i] = a_cone[i], l_cone[i]
        if active == 0:
            return passes
        ok, z, offsets, J, Ry, Yz, y, xp = _newton(
            x, K, xp_old, eq_old, cones, modes, dims, a0, l0, moduli, Q, PROJ, PDEV, VEC_I,
            SYM, scale, 1e-12, 60)
        if not ok:
            if not _after_failure(modes, z, offsets, dims, y, apex_tries, SYM):
                return -1
            continue
        _warm_starts(modes, z, offsets, dims, a_cone, l_cone, a_apex, l_apex)
        before = modes.copy()
        if _revise(modes, z, offsets, dims, xp, xp_old, y, cones, has_cone, eq_old, scale,
                   PDEV, SYM):
            for i in range(5):
                if before[i] == 2 and modes[i] == 1:
                    # off the apex onto the cone near it: start from the apex's increment
                    # with its deviator a little short (a deviatoric stress in its direction)
                    a_cone[i, 0] = a_apex[i, 0]
                    a_cone[i, 1:] = 0.99 * a_apex[i, 1:]
                    dev_dp = PDEV @ (xp[9 * i: 9 * i + 9] - xp_old[9 * i: 9 * i + 9])
                    l_cone[i] = math.sqrt(2.0 * np.dot(dev_dp, dev_dp))
            continue
        y_out[:] = y
        xp_out[:] = xp
        for i in range(5):
            if modes[i] != 0:
                eq_out[i] = eq_old[i] + z[offsets[i] + dims[i]]
            if modes[i] == 2:                         # the closed form's d_eq at the apex
                dev_dp = PDEV @ (xp[9 * i: 9 * i + 9] - xp_old[9 * i: 9 * i + 9])
                eq_out[i] += math.sqrt(2.0 * np.dot(dev_dp, dev_dp))
        if tangent:
            C_out[:, :] = K - Yz @ np.linalg.solve(J, Ry @ K)
        return passes
    return -1


@numba.njit(cache=True)
def _return_all(x, K, xp_old, eq_old, cones, has_cone, moduli, Q, PROJ, PDEV, VEC_I, SYM,
                y, C, xp, eq, flags, tangent):
    failed = 0
    for n in range(x.shape[0]):
        if tangent:
            C[n, :, :] = K
        if _return_one(x[n], K, xp_old[n], eq_old[n], cones, has_cone, moduli, Q, PROJ, PDEV,
                       VEC_I, SYM, y[n], C[n if tangent else 0], xp[n], eq[n], flags[n],
                       tangent) < 0:
            failed += 1
    return failed


def point_return(x, xp_old, eq_old, K, cones, has_cone, tangent: bool = True):
    """The return at n points.

    Args:
        x: measures (n, 45) (module docstring).
        xp_old: committed plastic measures (n, 45).
        eq_old: committed equivalent plastic strains (n, 5), one per level.
        K: :func:`stiffness` (45, 45).
        cones: (5, 4): ``A, B, k0, H`` of each level's cone.
        has_cone: (5,) bool: the level is plastic.
        tangent: compute the consistent tangents (False: ``C`` is None; a yielding point
            then skips a 45 x 45 solve, every point the tangent's 2025 values).

    Returns:
        ``(y, C, xp, eq, yielding, failed)``: stresses (n, 45), consistent tangents
        (n, 45, 45), plastic measures (n, 45), equivalent plastic strains (n, 5), 1.0 where a
        level's trial stress was outside its cone (n, 5), and the number of points whose
        return did not converge (their outputs hold the trial state).
    """
    x = np.ascontiguousarray(x, dtype=float)
    n = x.shape[0]
    y, C = np.empty((n, NX)), np.empty((n if tangent else 1, NX, NX))
    xp, eq, flags = np.empty((n, NX)), np.empty((n, LEVEL_COUNT)), np.empty((n, LEVEL_COUNT))
    K = np.ascontiguousarray(K, dtype=float)
    failed = _return_all(x, K, np.ascontiguousarray(xp_old, dtype=float),
                         np.ascontiguousarray(eq_old, dtype=float),
                         np.ascontiguousarray(cones, dtype=float), np.asarray(has_cone, dtype=bool),
                         level_moduli(K), _Q, _PROJ, _PDEV, _VEC_I, _SYMMETRIC, y, C, xp, eq, flags,
                         bool(tangent))
    return y, C if tangent else None, xp, eq, flags, int(failed)
