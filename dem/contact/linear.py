"""Linear spring-dashpot law with static/dynamic Coulomb friction (seed 003, eq. 4-6).

F_n = kn delta + gamma_n vn with gamma_n = 2 |beta(e)| sqrt(kn m*), which gives exactly the
requested restitution e for an unclipped binary collision; tangential spring kt with
dashpot gamma_t = 2 |beta| sqrt(kt m*), Coulomb-limited (`coulomb_tangential`).
"""

from __future__ import annotations

import math

from numba import njit

from dem.contact import P_BETA, P_CLIP, P_KN, P_KT, P_MUD, P_MUS
from dem.contact.kinematics import coulomb_tangential

__all__ = ["linear_force"]


@njit(cache=True, inline="always")
def linear_force(prm, delta, reff, meff, vn, vtx, vty, vtz, sx, sy, sz, slip, dt):
    """Common law signature. prm: pair row (NPARAM,); delta [m]; reff [m]; meff [kg];
    vn [m/s]; vt (3 scalars) [m/s]; spring s (3 scalars) [m]; slip flag; dt [s].

    Returns (fn, fnd, ftx, fty, ftz, fdx, fdy, fdz, sx, sy, sz, slip, e_n, e_pre, e_t,
    p_fric): normal force [N] (> 0 repulsive) and its dissipative part (dashpot and
    clipping), tangential force on j and its dissipative part [N] (dashpot, or all of it
    when sliding), new spring [m], slip flag, normal elastic energy [J], tangential spring
    energy before/after the increment [J], sliding power [W]. The elastic energy is
    consistent with the non-dissipative forces, so an energy ledger closes."""
    kn = prm[P_KN]
    kt = prm[P_KT]
    b = abs(prm[P_BETA])
    fel = kn * delta
    fn = fel + 2.0 * b * math.sqrt(kn * meff) * vn
    if prm[P_CLIP] != 0.0 and fn < 0.0:
        fn = 0.0
    gt = 2.0 * b * math.sqrt(kt * meff)
    ftx, fty, ftz, fdx, fdy, fdz, sx, sy, sz, slip, e_pre, e_t, p_fric = coulomb_tangential(
        kt, gt, prm[P_MUS], prm[P_MUD], fn, vtx, vty, vtz, sx, sy, sz, slip, dt)
    e_n = 0.5 * kn * delta * delta
    return (fn, fn - fel, ftx, fty, ftz, fdx, fdy, fdz, sx, sy, sz, slip, e_n, e_pre, e_t,
            p_fric)
