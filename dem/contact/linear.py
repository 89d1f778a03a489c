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


@njit(cache=True)
def linear_force(prm, delta, reff, meff, vn, vtx, vty, vtz, sx, sy, sz, slip, dt):
    """Common law signature. prm: pair row (NPARAM,); delta [m]; reff [m]; meff [kg];
    vn [m/s]; vt (3 scalars) [m/s]; spring s (3 scalars) [m]; slip flag; dt [s].

    Returns (fn, ftx, fty, ftz, sx, sy, sz, slip, e_el, p_damp, p_fric): normal force [N]
    (> 0 repulsive), tangential force on j [N], new spring, flag, elastic energy [J],
    power dissipated by damping (incl. normal force clipping) and by friction [W]."""
    kn = prm[P_KN]
    kt = prm[P_KT]
    b = abs(prm[P_BETA])
    fel = kn * delta
    fn = fel + 2.0 * b * math.sqrt(kn * meff) * vn
    if prm[P_CLIP] != 0.0 and fn < 0.0:
        fn = 0.0
    gt = 2.0 * b * math.sqrt(kt * meff)
    ftx, fty, ftz, sx, sy, sz, slip, e_t, p_d, p_f = coulomb_tangential(
        kt, gt, prm[P_MUS], prm[P_MUD], fn, vtx, vty, vtz, sx, sy, sz, slip, dt)
    e_el = 0.5 * kn * delta * delta + e_t
    p_damp = (fn - fel) * vn + p_d
    return fn, ftx, fty, ftz, sx, sy, sz, slip, e_el, p_damp, p_f
