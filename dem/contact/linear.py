"""Linear spring-dashpot law with static/dynamic Coulomb friction (seed 003, eq. 4-6).

F_n = kn delta + gamma_n vn with gamma_n = 2 |beta(e)| sqrt(kn m*), which gives exactly the
requested restitution e for an unclipped binary collision (vn: the speed at the end of the
step, `dem.contact.damping`); tangential spring kt with dashpot gamma_t = 2 |beta|
sqrt(kt m*), Coulomb-limited (`coulomb_tangential`).
"""

from __future__ import annotations

import math

from numba import njit

from dem.contact import P_BETA, P_CLIP, P_KN, P_KT, P_MUD, P_MUS
from dem.contact.damping import normal_dashpot
from dem.contact.kinematics import coulomb_tangential

__all__ = ["linear_force", "linear_law"]


@njit(cache=True, inline="always")
def linear_law(kn, kt, beta, mus, mud, clip, delta, reff, meff, vn, vtx, vty, vtz, sx, sy, sz,
               slip, dt, fo, vo, co, h):
    """The law on scalar parameters (kn, kt [N/m], beta(e), static and dynamic friction,
    clip flag) and dashpot history (fo, vo, co, h): what the pair loops call, so that
    no parameter-row view is made per contact (a view costs numba reference counting,
    atomic, in the hot loop). Other arguments and returns as `linear_force`."""
    b = abs(beta)
    fel = kn * delta
    fn, claim = normal_dashpot(fel, 2.0 * b * math.sqrt(kn * meff), vn, meff, fo, vo, co,
                               h, delta, 0.0)
    if clip != 0.0 and fn < 0.0:
        fn = 0.0
    gt = 2.0 * b * math.sqrt(kt * meff)
    ftx, fty, ftz, fdx, fdy, fdz, sx, sy, sz, slip, e_pre, e_t, p_fric = coulomb_tangential(
        kt, gt, mus, mud, fn, vtx, vty, vtz, sx, sy, sz, slip, dt)
    e_n = 0.5 * kn * delta * delta
    return (fn, fn - fel, ftx, fty, ftz, fdx, fdy, fdz, sx, sy, sz, slip, e_n, e_pre, e_t,
            p_fric, claim)


@njit(cache=True, inline="always")
def linear_force(prm, delta, reff, meff, vn, vtx, vty, vtz, sx, sy, sz, slip, dt, fo=0.0,
                 vo=0.0, co=0.0, h=0.0):
    """Common law signature. prm: pair row (NPARAM,); delta [m]; reff [m]; meff [kg];
    vn [m/s]; vt (3 scalars) [m/s]; spring s (3 scalars) [m]; slip flag; dt [s]; the normal
    force fo [N], vn vo [m/s] and release claim co of the last force pass and the prediction
    horizon h [s] of the dashpot (`dem.contact.damping.normal_dashpot`; h = 0: on vn as
    given).

    Returns (fn, fnd, ftx, fty, ftz, fdx, fdy, fdz, sx, sy, sz, slip, e_n, e_pre, e_t,
    p_fric, claim): normal force [N] (> 0 repulsive) and its dissipative part (dashpot and
    clipping), tangential force on j and its dissipative part [N] (dashpot, or all of it
    when sliding), new spring [m], slip flag, normal elastic energy [J], tangential spring
    energy before/after the increment [J], sliding power [W], the dashpot's release claim
    for the next pass (history). The elastic energy is
    consistent with the non-dissipative forces, so an energy ledger closes."""
    return linear_law(prm[P_KN], prm[P_KT], prm[P_BETA], prm[P_MUS], prm[P_MUD], prm[P_CLIP],
                      delta, reff, meff, vn, vtx, vty, vtz, sx, sy, sz, slip, dt, fo, vo, co, h)
