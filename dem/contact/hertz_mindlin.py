"""Hertz-Mindlin law with tangential history (LIGGGHTS ``model hertz tangential history``).

With a = sqrt(R* delta): F_n = 4/3 E* a delta + gamma_n vn (vn: the speed at the end of
the step, `dem.contact.damping`),
gamma_n = 2 sqrt(5/6) |beta(e)| sqrt(S_n m*), S_n = 2 E* a (Tsuji et al. 1992 form used by
LIGGGHTS); tangential spring k_t = 8 G* a with gamma_t = 2 sqrt(5/6) |beta| sqrt(k_t m*),
Coulomb limit with history rescaling (`coulomb_tangential`). Elastic normal energy
8/15 E* sqrt(R*) delta^(5/2). Parameters for quartz: seed 002 Table 1.
"""

from __future__ import annotations

import math

from numba import njit

from dem.contact import P_BETA, P_CLIP, P_ESTAR, P_GSTAR, P_MUD, P_MUS
from dem.contact.damping import normal_dashpot
from dem.contact.kinematics import coulomb_tangential

__all__ = ["hertz_mindlin_force", "hertz_mindlin_law"]

_C = 2.0 * math.sqrt(5.0 / 6.0)


@njit(cache=True, inline="always")
def hertz_mindlin_law(estar, gstar, beta, mus, mud, clip, delta, reff, meff, vn, vtx, vty,
                      vtz, sx, sy, sz, slip, dt, fo, vo, co, h):
    """The law on scalar parameters (E*, G* [Pa], beta(e), static and dynamic friction, clip
    flag) and history (fo, vo, co, h), as `dem.contact.linear.linear_law`."""
    a = math.sqrt(reff * delta)
    b = abs(beta)
    fel = 4.0 / 3.0 * estar * a * delta
    fn, claim = normal_dashpot(fel, _C * b * math.sqrt(2.0 * estar * a * meff), vn, meff, fo,
                               vo, co, h, delta, 0.25)
    if clip != 0.0 and fn < 0.0:
        fn = 0.0
    kt = 8.0 * gstar * a
    gt = _C * b * math.sqrt(kt * meff)
    ftx, fty, ftz, fdx, fdy, fdz, sx, sy, sz, slip, e_pre, e_t, p_fric = coulomb_tangential(
        kt, gt, mus, mud, fn, vtx, vty, vtz, sx, sy, sz, slip, dt)
    e_n = 0.4 * fel * delta
    return (fn, fn - fel, ftx, fty, ftz, fdx, fdy, fdz, sx, sy, sz, slip, e_n, e_pre, e_t,
            p_fric, claim)


@njit(cache=True, inline="always")
def hertz_mindlin_force(prm, delta, reff, meff, vn, vtx, vty, vtz, sx, sy, sz, slip, dt,
                        fo=0.0, vo=0.0, co=0.0, h=0.0):
    """Common law signature, see `dem.contact.linear.linear_force`."""
    return hertz_mindlin_law(prm[P_ESTAR], prm[P_GSTAR], prm[P_BETA], prm[P_MUS], prm[P_MUD],
                             prm[P_CLIP], delta, reff, meff, vn, vtx, vty, vtz, sx, sy, sz,
                             slip, dt, fo, vo, co, h)
