"""Velocity Verlet with rotations, and `Simulation`: particles + materials + walls + gravity.

One step (half-kick / drift / force / half-kick): v += dt/2 a, w += dt/2 T/I; x += dt v;
forces at the new positions; v += dt/2 a, w += dt/2 T/I. Only FREE particles move; GHOST
particles keep the x, v, omega written from outside (their contact forces are still in
``force``/``torque``); FIXED particles never move. Gravity enters the acceleration, not
``force``, so ``force`` holds contact forces only (what the coupling layer reads).
"""

from __future__ import annotations

import math
import os
import tempfile

import numpy as np
from numba import get_num_threads, njit, prange

from dem.contact import ContactMaterial, pair_table
from dem.drag import group_drag
from dem.errors import BlowUpError, DomainError, OverlapError
from dem.forces import (
    NO_CELL,
    NOUT,
    PARALLEL_MIN,
    WALL_PARALLEL_MIN,
    _pair_csr,
    _wall_all,
    pair_forces,
    pair_layout,
    refresh_live,
    spread,
    wall_forces,
)
from dem.neighbours import NeighbourList
from dem.prescribed import _prescribe
from dem.state import FREE, GHOST
from dem.timestep import DEFAULT_SAFETY, choose_dt, critical_dt
from dem.walls import WallSet

__all__ = ["Simulation"]

_NO_L, _NO_O, _EMPTY = np.zeros((3, 3)), np.zeros(3), np.zeros((0, 3))
_NO_DRAG = (False, np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(3),
            np.zeros(0), _EMPTY, _EMPTY, _EMPTY)   # the types of `GroupDrag.arrays`
_NO_PK = (np.zeros(0, np.int64), np.zeros(0, np.int64), _EMPTY, _EMPTY, _EMPTY, _EMPTY, _EMPTY,
          np.zeros(0, np.bool_), np.zeros((1, 1, 2)))
"""`dem.prescribed.Prescribed.pack` of no motion (the types `_steps` takes)."""

# The kernels below are written out in full: per-particle helper functions (inlined by
# numba's IR inliner or left to LLVM) made these loops several times slower.
#
# hit (n,) int8 flags the particles that received a contact in the last force pass (set
# by `dem.forces`): the others have zero force, torque, fe, fd, td, so `_kick` and
# `_kick_drift` neither read nor clear their force rows and leave their spin alone
# (v += h (0/m + g) is v += h g to the bit, omega += h 0/I is omega). `_drift` reads and
# clears every row whatever the flags say (the arrays may have been written from outside
# between two calls of `Simulation.step`).

@njit(cache=True)
def _drift(x, v, omega, force, torque, fe, fd, td, mass, inertia, kind, g, h, dt, per, lg,
           org, x0, hit):
    """First half-kick v += h (F/m + g), omega += h T/I and drift x += dt (v + [L (x - o)])
    of FREE particles; the forces still in the arrays (the last evaluation) do their half
    of the trapezoidal work over the step's displacement, then every particle's force,
    torque, fe, fd, td and hit flag are cleared for the next force pass. Returns the work
    [J] of all contact forces, of their conservative normal parts and of their damping
    parts (this half), and the largest squared displacement [m^2] from x0 (the neighbour
    list's build positions; 0 if x0 is empty)."""
    wc = 0.0
    we = 0.0
    wd = 0.0
    d2 = 0.0
    track = x0.shape[0] == x.shape[0]
    for i in range(v.shape[0]):
        if kind[i] == 0:
            for c in range(3):
                v[i, c] += h * (force[i, c] / mass[i] + g[c])
                omega[i, c] += h * torque[i, c] / inertia[i]
            if per:
                ax = x[i, 0] - org[0]
                ay = x[i, 1] - org[1]
                az = x[i, 2] - org[2]
                for c in range(3):
                    x[i, c] += dt * (v[i, c] + lg[c, 0] * ax + lg[c, 1] * ay + lg[c, 2] * az)
            else:
                for c in range(3):
                    x[i, c] += dt * v[i, c]
            for c in range(3):
                dx = h * v[i, c]  # half of the displacement: the trapezoid's 1/2
                dq = h * omega[i, c]
                wc += force[i, c] * dx + torque[i, c] * dq
                we += fe[i, c] * dx
                wd += fd[i, c] * dx + td[i, c] * dq
        if track:
            a0 = x[i, 0] - x0[i, 0]
            a1 = x[i, 1] - x0[i, 1]
            a2 = x[i, 2] - x0[i, 2]
            d2 = max(d2, a0 * a0 + a1 * a1 + a2 * a2)
        for c in range(3):
            force[i, c] = torque[i, c] = fe[i, c] = fd[i, c] = td[i, c] = 0.0
        hit[i] = 0
    return wc, we, wd, d2


@njit(cache=True)
def _add_external(rows, f, force, hit):
    """The external forces f (k, 3) [N] added to the force rows ``rows`` (k,), flagged for
    the kicks (numba: with a force on every grain, numpy's gathers cost 40 % of a dense step)."""
    for k in range(rows.shape[0]):
        i = rows[k]
        for c in range(3):
            force[i, c] += f[k, c]
        hit[i] = 1


@njit(cache=True)
def _external_work(rows, f, x, x0):
    """Work [J] of the external forces f (k, 3) on rows ``rows`` since positions x0 (k, 3),
    which are moved on to x."""
    w = 0.0
    for k in range(rows.shape[0]):
        i = rows[k]
        for c in range(3):
            w += f[k, c] * (x[i, c] - x0[k, c])
            x0[k, c] = x[i, c]
    return w


@njit(cache=True)
def _kick(v, omega, force, torque, fe, fd, td, mass, inertia, kind, g, h, hit):
    """Second half-kick of FREE particles, after booking the new forces' half of the
    trapezoidal work over the step's displacement dt v (v = the half-step velocity, what
    the drift used; the drift booked the old forces' half, (F_old + F_new)/2 . dx in all).
    Returns the work [J] of this half of all contact forces, of their conservative normal
    parts, of their damping parts, and the work of gravity over the step.

    With K~ = K - sum h^2/(2m) |F_tot|^2 - h^2/(2I) |T|^2 (h = dt/2) velocity Verlet gives
    exactly K~_new - K~_old = sum (F_old + F_new)/2 . dx + (T_old + T_new)/2 . dtheta."""
    wc = 0.0
    we = 0.0
    wd = 0.0
    wg = 0.0
    for i in range(v.shape[0]):
        if kind[i] != 0:
            continue
        if hit[i] == 0:
            for c in range(3):
                wg += 2.0 * mass[i] * g[c] * (h * v[i, c])
                v[i, c] += h * g[c]
            continue
        for c in range(3):
            dx = h * v[i, c]
            dq = h * omega[i, c]
            wc += force[i, c] * dx + torque[i, c] * dq
            we += fe[i, c] * dx
            wd += fd[i, c] * dx + td[i, c] * dq
            wg += 2.0 * mass[i] * g[c] * dx
            v[i, c] += h * (force[i, c] / mass[i] + g[c])
            omega[i, c] += h * torque[i, c] / inertia[i]
    return wc, we, wd, wg


@njit(cache=True)
def _kick_drift_range(lo, hi, x, v, omega, force, torque, fe, fd, td, mass, inertia, kind, g,
                      h, dt, per, lg, org, x0, hit, res):
    """`_kick` of one step and `_drift` of the next in one pass over particles lo:hi (the
    same arithmetic in the same order: the same bits as the two kernels in turn), reading
    and clearing only the flagged force rows. res (8,) receives the kick's four works, the
    drift's three and its largest squared displacement [m^2]."""
    kc = 0.0
    ke = 0.0
    kd = 0.0
    kg = 0.0
    wc = 0.0
    we = 0.0
    wd = 0.0
    d2 = 0.0
    s0 = s1 = s2 = 0.0  # momentum sum m v (half-step) for the work of gravity
    hg0 = h * g[0]
    hg1 = h * g[1]
    hg2 = h * g[2]
    track = x0.shape[0] == x.shape[0]
    for i in range(lo, hi):
        if hit[i] == 0:
            if kind[i] == 0:  # no contact: v += h (0/m + g) twice, to the bit
                mi = mass[i]
                u0 = v[i, 0]
                u1 = v[i, 1]
                u2 = v[i, 2]
                s0 += mi * u0
                s1 += mi * u1
                s2 += mi * u2
                u0 += hg0
                u1 += hg1
                u2 += hg2
                u0 += hg0
                u1 += hg1
                u2 += hg2
                v[i, 0] = u0
                v[i, 1] = u1
                v[i, 2] = u2
                if per:
                    ax = x[i, 0] - org[0]
                    ay = x[i, 1] - org[1]
                    az = x[i, 2] - org[2]
                    for c in range(3):
                        x[i, c] += dt * (v[i, c] + lg[c, 0] * ax + lg[c, 1] * ay
                                         + lg[c, 2] * az)
                else:
                    for c in range(3):
                        x[i, c] += dt * v[i, c]
        else:
            if kind[i] == 0:
                for c in range(3):  # the kick
                    dx = h * v[i, c]
                    dq = h * omega[i, c]
                    kc += force[i, c] * dx + torque[i, c] * dq
                    ke += fe[i, c] * dx
                    kd += fd[i, c] * dx + td[i, c] * dq
                    kg += 2.0 * mass[i] * g[c] * dx
                    v[i, c] += h * (force[i, c] / mass[i] + g[c])
                    omega[i, c] += h * torque[i, c] / inertia[i]
                for c in range(3):  # the next drift
                    v[i, c] += h * (force[i, c] / mass[i] + g[c])
                    omega[i, c] += h * torque[i, c] / inertia[i]
                if per:
                    ax = x[i, 0] - org[0]
                    ay = x[i, 1] - org[1]
                    az = x[i, 2] - org[2]
                    for c in range(3):
                        x[i, c] += dt * (v[i, c] + lg[c, 0] * ax + lg[c, 1] * ay
                                         + lg[c, 2] * az)
                else:
                    for c in range(3):
                        x[i, c] += dt * v[i, c]
                for c in range(3):
                    dx = h * v[i, c]
                    dq = h * omega[i, c]
                    wc += force[i, c] * dx + torque[i, c] * dq
                    we += fe[i, c] * dx
                    wd += fd[i, c] * dx + td[i, c] * dq
            for c in range(3):
                force[i, c] = torque[i, c] = fe[i, c] = fd[i, c] = td[i, c] = 0.0
            hit[i] = 0
        if track:
            a0 = x[i, 0] - x0[i, 0]
            a1 = x[i, 1] - x0[i, 1]
            a2 = x[i, 2] - x0[i, 2]
            d2 = max(d2, a0 * a0 + a1 * a1 + a2 * a2)
    res[0] = kc
    res[1] = ke
    res[2] = kd
    res[3] = kg + 2.0 * h * (g[0] * s0 + g[1] * s1 + g[2] * s2)
    res[4] = wc
    res[5] = we
    res[6] = wd
    res[7] = d2


KD_CHUNK = 256
"""Particles per task of `_kick_drift_par` (fixed: its sums do not depend on threads)."""
KD_PARALLEL_MIN = 4096
"""Particles from which, with more than one numba thread, `_kick_drift_par` runs (below, a
thread rendezvous costs more than the pass; see `dem.forces.PARALLEL_MIN`)."""


@njit(cache=True)
def _kick_drift(x, v, omega, force, torque, fe, fd, td, mass, inertia, kind, g, h, dt, per,
                lg, org, x0, hit, res):
    """`_kick_drift_range` over all particles; res (8,)."""
    _kick_drift_range(0, x.shape[0], x, v, omega, force, torque, fe, fd, td, mass, inertia,
                      kind, g, h, dt, per, lg, org, x0, hit, res)


@njit(parallel=True, cache=True)
def _kick_drift_par(x, v, omega, force, torque, fe, fd, td, mass, inertia, kind, g, h, dt,
                    per, lg, org, x0, hit, res):
    """`_kick_drift` in chunks of KD_CHUNK particles over the threads; the chunks' sums are
    added in chunk order (the same for any thread count; the trajectory is the same bits as
    the serial kernel, the ledger sums differ from it by round-off)."""
    n = x.shape[0]
    nb = (n + KD_CHUNK - 1) // KD_CHUNK
    part = np.zeros((nb, 8))
    for t in prange(nb):
        b = spread(t, nb)  # loaded and idle grains shared out (see `dem.forces.SPREAD`)
        _kick_drift_range(b * KD_CHUNK, min(n, (b + 1) * KD_CHUNK), x, v, omega, force,
                          torque, fe, fd, td, mass, inertia, kind, g, h, dt, per, lg, org, x0,
                          hit, part[b])
    for q in range(8):
        res[q] = 0.0
    for b in range(nb):
        for q in range(7):
            res[q] += part[b, q]
        res[7] = max(res[7], part[b, 7])


@njit(cache=True)
def _wall_work(wf0, wf1, p0, p1):
    """Work [J] of the contacts on the walls over their displacement p1 - p0 (nw, 3), by
    the trapezoidal rule, of the total, conservative normal and damping resultants (nw, 9)."""
    w = np.zeros(3)
    for k in range(wf0.shape[0]):
        for c in range(3):
            d = 0.5 * (p1[k, c] - p0[k, c])
            for q in range(3):
                w[q] += (wf0[k, 3 * q + c] + wf1[k, 3 * q + c]) * d
    return w[0], w[1], w[2]


@njit(cache=True)
def _kinetic_finite(x, v, omega, mass, inertia, kind):
    """Kinetic energy [J] of the FREE particles (translational + rotational; for the
    blow-up test, `Simulation.energy` reports the parts) and whether x, v, omega are all
    finite."""
    ke = 0.0
    ok = True
    for i in range(x.shape[0]):
        for c in range(3):
            if not (math.isfinite(x[i, c]) and math.isfinite(v[i, c])
                    and math.isfinite(omega[i, c])):
                ok = False
        if kind[i] == 0:
            ke += 0.5 * (mass[i] * (v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2])
                         + inertia[i] * (omega[i, 0] * omega[i, 0] + omega[i, 1] * omega[i, 1]
                                         + omega[i, 2] * omega[i, 2]))
    return ke, ok


@njit(cache=True)
def _branch_force_sums(pi, pj, img, out, x, h, x0, h0, hinv, bf, bf0):
    """bf[q] += b (x) f_q and bf0[q] += b0 (x) f_q (3, 3, 3) over the touching rows of
    out: f_0, f_1, f_2 the contact force on i by j, its conservative normal and its damping
    parts, b = x_j - x_i + h img [m], b0 the same at positions x0 and cell h0 (3, 3), with
    a particle's jump into the cell since x0 (whole cell vectors, hinv = h^-1) undone."""
    b = np.empty(3)
    b0 = np.empty(3)
    sh = np.empty(3)
    for k in range(pi.shape[0]):
        if out[k, 18] == 0.0:
            continue
        i = pi[k]
        j = pj[k]
        for a in range(3):  # image shift of j as seen from x0
            ji = 0.0
            jj = 0.0
            for c in range(3):
                ji += hinv[a, c] * (x0[i, c] - x[i, c])
                jj += hinv[a, c] * (x0[j, c] - x[j, c])
            sh[a] = img[k, a] + np.round(jj) - np.round(ji)
        for a in range(3):
            b[a] = x[j, a] - x[i, a]
            b0[a] = x0[j, a] - x0[i, a]
            for c in range(3):
                b[a] += h[a, c] * img[k, c]
                b0[a] += h0[a, c] * sh[c]
        for q in range(3):
            col = 0 if q == 0 else (19 if q == 1 else 9)
            for a in range(3):
                for c in range(3):
                    f = -out[k, col + c]
                    bf[q, a, c] += b[a] * f
                    bf0[q, a, c] += b0[a] * f


_STATE_KEYS = ("x", "v", "omega", "radius", "mass", "inertia", "material", "kind", "force",
               "torque")


def _fit(key, a, shape):
    """A (array-like) checked to have ``shape`` (None: empty) for the state entry ``key``."""
    a = np.asarray(a)
    if (a.size != 0) if shape is None else (a.shape != tuple(shape)):
        raise ValueError(f"state {key!r} has shape {a.shape}, this Simulation needs "
                         f"{'an empty array' if shape is None else tuple(shape)}")
    return a


def _section(d, prefix, exclude=()):
    """The entries of d under ``prefix`` (prefix stripped), but the ``exclude`` names."""
    n = len(prefix)
    return {k[n:]: v for k, v in d.items() if k.startswith(prefix) and k[n:] not in exclude}


@njit(cache=True)
def _gather_ghosts(g, force, torque, fe, fd, td, out):
    """Out (ng, 15) <- force, torque, fe, fd, td of the GHOST rows ``g``."""
    for k in range(g.shape[0]):
        i = g[k]
        for c in range(3):
            out[k, c] = force[i, c]
            out[k, 3 + c] = torque[i, c]
            out[k, 6 + c] = fe[i, c]
            out[k, 9 + c] = fd[i, c]
            out[k, 12 + c] = td[i, c]
    return out


@njit(cache=True)
def _gather_rows(g, a, out):
    """Out (ng, 3) <- a[g]."""
    for k in range(g.shape[0]):
        for c in range(3):
            out[k, c] = a[g[k], c]
    return out


@njit(cache=True)
def _ghost_work(prev, now, xg0, xg1, omega, g, dt):
    """Work [J] of the contacts on the GHOST rows ``g`` over one step, by the trapezoidal
    rule between their force rows ``prev`` and ``now`` (ng, 15: force, torque, fe, fd, td)
    over the displacement xg1 - xg0 and the rotation dt omega: all, the conservative normal
    part, the damping part."""
    wa = 0.0
    we = 0.0
    wd = 0.0
    for k in range(g.shape[0]):
        i = g[k]
        for c in range(3):
            dx = xg1[k, c] - xg0[k, c]
            dq = dt * omega[i, c]
            wa += (prev[k, c] + now[k, c]) * dx + (prev[k, 3 + c] + now[k, 3 + c]) * dq
            we += (prev[k, 6 + c] + now[k, 6 + c]) * dx
            wd += (prev[k, 9 + c] + now[k, 9 + c]) * dx + (prev[k, 12 + c] + now[k, 12 + c]) * dq
    return 0.5 * wa, 0.5 * we, 0.5 * wd


@njit(cache=True)
def _damp(v, omega, mass, inertia, kind, decay):
    """v, omega <- decay v, decay omega of the FREE particles; returns the kinetic energy
    this takes out [J]."""
    ke = 0.0
    for i in range(v.shape[0]):
        if kind[i] != 0:
            continue
        ke += 0.5 * (mass[i] * (v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2])
                     + inertia[i] * (omega[i, 0] * omega[i, 0] + omega[i, 1] * omega[i, 1]
                                     + omega[i, 2] * omega[i, 2]))
        for c in range(3):
            v[i, c] *= decay
            omega[i, c] *= decay
    return (1.0 - decay * decay) * ke


# The fused stepping loop: `Simulation.step` without a hook, damping or a periodic cell, on
# the serial drivers, runs its steps here between two
# neighbour builds and checks, one numba call instead of about ten dispatches and the
# Python bookkeeping of each step (the fixed cost of a step: 512 spheres without contacts,
# see benchmarks/dem_throughput.py). The same kernels in the same order as the Python loop
# of `step`, so the same bits; the ledger's additions are written out as `_book` does them.

@njit(cache=True)
def _walls_moved2(wp, wu, wp0, dt):
    """Largest squared displacement [m^2] of the wall points wp advanced by dt wu from wp0
    (`dem.neighbours._max_disp2` after `WallSet.advance`, to the bit)."""
    d2 = 0.0
    for w in range(wp.shape[0]):
        a0 = (wp[w, 0] + dt * wu[w, 0]) - wp0[w, 0]
        a1 = (wp[w, 1] + dt * wu[w, 1]) - wp0[w, 1]
        a2 = (wp[w, 2] + dt * wu[w, 2]) - wp0[w, 2]
        d2 = max(d2, a0 * a0 + a1 * a1 + a2 * a2)
    return d2


@njit(cache=True)
def _wall_pass(wi, ww, x, v, omega, radius, mass, material, wp, wn, wu, wcol, table, whist,
               wslip, wetan, dt, h, force, torque, fe, fd, td, wf, wf_prev, wforce, hit):
    """A step's walls as `Simulation.step` and `dem.forces.wall_forces` run them serially:
    points advanced by dt wu, the resultants wf kept in wf_prev, the new ones into wf and
    their forces into wforce. Returns (elastic, spring) [J]."""
    for w in range(wp.shape[0]):
        for c in range(3):
            wp[w, c] += dt * wu[w, c]
    wf_prev[:] = wf
    wf[:] = 0.0
    e = es = 0.0
    if wi.shape[0]:
        e, es = _wall_all(wi, ww, x, v, omega, radius, mass, material, wp, wn, wu, wcol,
                          table, whist, wslip, wetan, dt, h, force, torque, fe, fd, td, wf,
                          hit)
    wforce[:] = wf[:, :3]
    return e, es


LED_KEYS = ("dissipated", "friction", "walls", "gravity", "external", "ghosts")
"""The ledger terms `_steps` adds to, in its array's order (after time, elastic, spring and
the pending drift's four values: `Simulation._fused`)."""


@njit(cache=True)
def _steps(s, n, check_every, x, v, omega, force, torque, fe, fd, td, mass, inertia, kind, g,
           h, dt, x0, hit, radius, material, table, start, pj32, live, hist, slip, etan, wi,
           ww, wp, wn, wu, wcol, whist, wslip, wetan, wf, wf_prev, wp_at, wforce, wp0, skin,
           ext, erows, ef, ex0, drag, dgroup, dweight, dwdt_m, dalpha, daxes, dscale, dshift,
           dsu, dout, presc, pr_rows, pr_group, pr_base, pr_a, pr_b, pr_vel, pr_om,
           pr_setom, pr_coef, gh, gprev, gnow, xg_at, xg_now, st, ist):
    """Steps s, s + 1, ... of a `Simulation.step` call of n steps, until n are done, a
    blow-up check is due (after the step that ends on a multiple of check_every: its second
    half-kick is `_kick`, the next drift is left to the next call) or the neighbour list
    needs a rebuild before a force pass (then that step's drift is done and pending, and
    the caller does the rest of the step). Pairs over the compact layout (start, pj32,
    live: `dem.forces.pair_layout`), walls (points wp advanced by dt wu, resultants wf,
    last ones wf_prev, points at the last pass wp_at, wforce = the walls' force rows),
    external forces if ext (rows erows, forces ef, positions at the last pass ex0), a
    group drag if drag (`dem.drag.GroupDrag`'s arrays, applied where `step` applies it),
    prescribed motions if presc (`dem.prescribed.Prescribed.pack`), the GHOST rows gh
    (force rows of the last pass gprev, valid if ist[3], and of this one gnow (ng, 15);
    positions at the last pass xg_at and at this one xg_now (ng, 3)). st (13,) float:
    time, elastic, spring, the pending drift's works and squared displacement (4), the
    ledger terms of LED_KEYS; ist (4,) int: step count, pending flag, steps done (out),
    gprev valid. x0, wp0: the neighbour list's build positions; skin [m]."""
    nw = wp.shape[0]
    res = np.empty(8)
    lg = np.zeros((3, 3))
    org = np.zeros(3)
    nsteps = ist[0]
    pend = ist[1]
    done = 0
    wc0 = st[3]
    we0 = st[4]
    wd0 = st[5]
    d2 = st[6]
    ng = gh.shape[0]
    while s < n:
        if pend == 0:
            if presc:
                _prescribe(s, pr_rows, pr_group, pr_base, pr_a, pr_b, pr_vel, pr_om, pr_setom,
                           pr_coef, x, v, omega)
            if ng and ist[3] == 0:  # (else the last step's: the kick keeps forces)
                _gather_ghosts(gh, force, torque, fe, fd, td, gprev)
                ist[3] = 1
            wc0, we0, wd0, d2 = _drift(x, v, omega, force, torque, fe, fd, td, mass,
                                       inertia, kind, g, h, dt, 0, lg, org, x0, hit)
            pend = 1
        # `NeighbourList.needs_rebuild` at the walls' points after this step's advance
        d = math.sqrt(d2)
        if nw:
            d += math.sqrt(_walls_moved2(wp, wu, wp0, dt))
        if d > 0.5 * skin:
            break
        e1, s1 = _pair_csr(start, pj32, live, x, v, omega, radius, mass, material, table,
                           hist, slip, etan, dt, h, force, torque, fe, fd, td, hit)
        e2, s2 = _wall_pass(wi, ww, x, v, omega, radius, mass, material, wp, wn, wu, wcol,
                            table, whist, wslip, wetan, dt, h, force, torque, fe, fd, td, wf,
                            wf_prev, wforce, hit)
        if ext:
            _add_external(erows, ef, force, hit)
        if ng:
            _gather_ghosts(gh, force, torque, fe, fd, td, gnow)
            _gather_rows(gh, x, xg_now)
        if drag:
            group_drag(v, force, g, dt, dgroup, dweight, dwdt_m, dalpha, daxes, dscale, dshift,
                       dsu, dout, hit)
        e = e1 + e2
        es = s1 + s2
        final = s == n - 1 or (nsteps + 1) % check_every == 0
        if final:
            wc1, we1, wd1, wg = _kick(v, omega, force, torque, fe, fd, td, mass, inertia, kind,
                                      g, h, hit)
            pend = 0
        else:
            if presc:  # the next step's motions, before its drift
                _prescribe(s + 1, pr_rows, pr_group, pr_base, pr_a, pr_b, pr_vel, pr_om,
                           pr_setom, pr_coef, x, v, omega)
            _kick_drift(x, v, omega, force, torque, fe, fd, td, mass, inertia, kind, g, h, dt,
                        0, lg, org, x0, hit, res)
            wc1 = res[0]
            we1 = res[1]
            wd1 = res[2]
            wg = res[3]
        # `Simulation._book` without a cell (its zeros added as it adds them)
        wc = wc0 + wc1
        we = we0 + we1
        wd = wd0 + wd1
        wgh = wge = wgd = 0.0
        if ng:
            wgh, wge, wgd = _ghost_work(gprev, gnow, xg_at, xg_now, omega, gh, dt)
            gprev[:] = gnow
            xg_at[:] = xg_now
        www = wwe = wwd = 0.0
        if nw:
            www, wwe, wwd = _wall_work(wf_prev, wf, wp_at, wp)
            wp_at[:] = wp
        contact = wc + wgh + www - 0.0
        if ext:
            wext = _external_work(erows, ef, x, ex0)
            contact -= wext
            st[11] += wext
        dissipated = -(contact - (we + wge + wwe - 0.0)) - (es - st[2])
        damping = -(wd + wgd + wwd - 0.0)
        st[7] += dissipated
        st[8] += dissipated - damping
        st[9] -= www
        st[10] += wg
        st[12] -= wgh
        st[1] = e
        st[2] = es
        st[0] += dt
        nsteps += 1
        s += 1
        done += 1
        if final:
            break
        wc0 = res[4]
        we0 = res[5]
        wd0 = res[6]
        d2 = res[7]
    st[3] = wc0
    st[4] = we0
    st[5] = wd0
    st[6] = d2
    ist[0] = nsteps
    ist[1] = pend
    ist[2] = done


class Simulation:
    """A DEM run: particles, contact materials, planar walls, gravity and a time step.

    Args:
        particles: `dem.state.Particles` (modified in place).
        materials: a `ContactMaterial` or a list indexed by ``particles.material``.
        walls: `dem.walls.PlaneWall` list. gravity: (3,) [m/s^2].
        dt: time step [s]; None: ``safety * critical_dt`` (safety None:
            `dem.timestep.DEFAULT_SAFETY` of the law); above critical raises
            `TimeStepError` unless ``force_dt``. v_max: expected impact speed [m/s] for
            the Hertz estimate. skin: Verlet skin [m] (default 0.1 x largest diameter).
        domain: ((3,), (3,)) box; a FREE particle leaving it raises `DomainError`.
        allow_overlap: accept initial overlaps (else `OverlapError`).
        blowup_factor, check_every: every ``check_every`` steps a NaN, or a kinetic energy
            above ``blowup_factor`` x the energy put in so far, raises `BlowUpError` after
            writing the last good state to ``state_path`` (default
            ``<tempdir>/dem_last_good_state_<pid>.npz``, not the working directory: a
            library call should not litter it; the error names the file).
        cell: a `dem.periodic.PeriodicCell` (then ``p.v`` are fluctuations about the
            cell's affine velocity field; no walls, ghosts or domain box).
        prescribed_pairs: evaluate contacts between two particles that are not FREE (GHOST
            or FIXED). False skips them: they move no particle, and the force on a GHOST row
            is then what the FREE particles (and walls) exert on it, the reaction a
            partitioned coupling hands its continuum.
    """

    def __init__(self, particles, materials, walls=(), gravity=(0.0, 0.0, 0.0), dt=None, *,
                 safety=None, force_dt=False, v_max=None, skin=None, domain=None,
                 allow_overlap=False, blowup_factor=10.0, check_every=100, state_path=None,
                 cell=None, prescribed_pairs=True):
        self.p = particles
        self.prescribed_pairs = bool(prescribed_pairs)
        mats = [materials] if isinstance(materials, ContactMaterial) else list(materials)
        if particles.material.max(initial=0) >= len(mats):
            raise ValueError(f"particles.material refers to material "
                             f"{particles.material.max()} but only {len(mats)} given")
        self.materials, self.table = mats, pair_table(mats)
        self.walls = WallSet(walls)
        if len(self.walls) and self.walls.material.max() >= len(mats):
            raise ValueError("a PlaneWall.material index is beyond the material list")
        g = np.asarray(gravity, float)
        if particles.dim == 2 and g.shape == (2,):
            g = np.append(g, 0.0)
        if g.shape != (3,) or not np.isfinite(g).all():
            raise ValueError(f"gravity must be 3 finite numbers [m/s^2] (2 or 3 in 2D, z = 0), "
                             f"got {gravity!r}")
        self.gravity = g
        if particles.dim == 2 and self.gravity[2] != 0:
            raise ValueError("gravity[2] must be 0 for 2D disks")
        self.cell = cell
        if cell is not None:
            if cell.dim != particles.dim:
                raise ValueError(f"cell: a {cell.dim}D PeriodicCell for {particles.dim}D "
                                 f"particles")
            if len(self.walls) or domain is not None or (particles.kind == GHOST).any():
                raise ValueError("cell: a periodic cell takes no walls, domain box or GHOST "
                                 "particles")
        self.dt_crit = critical_dt(particles, mats, v_max)
        if safety is None:
            safety = DEFAULT_SAFETY[mats[0].law]
        self.dt = choose_dt(dt, self.dt_crit, safety, force_dt)
        skin = 0.2 * float(particles.radius.max()) if skin is None else float(skin)
        self.nl = NeighbourList(particles.n, skin)
        self.domain = None if domain is None else np.asarray(domain, float).reshape(2, 3)
        self.blowup_factor, self.check_every = float(blowup_factor), int(check_every)
        self.state_path = state_path or os.path.join(tempfile.gettempdir(),
                                                  f"dem_last_good_state_{os.getpid()}.npz")
        if cell is None and not allow_overlap:
            # round-off contacts (1e-9 of a radius) are not overlaps
            particles.check_overlaps(allow=allow_overlap, tol=1e-9 * float(particles.radius.max()))
        self.time, self.nsteps = 0.0, 0
        self.damping_removed = 0.0   # kinetic energy taken out by step(decay=...) [J]
        self._ghosts = self._ghost_index()
        n = particles.n
        self._led = dict(dissipated=0.0, friction=0.0, walls=0.0, ghosts=0.0, gravity=0.0,
                         cell=0.0, external=0.0)
        # constant external forces on FREE rows (`set_external_force`): (rows, forces, rows'
        # positions at the last force pass) or None
        self._ext = None
        # contact sums b (x) f (`_stress_sums`): of the last force pass, of the one before,
        # and of the last forces with the branch vectors of the pass before
        self._bf = self._bf_prev = self._bf_mixed = np.zeros((3, 3, 3))
        self._xh = None  # positions and cell vectors of the last force pass
        self._fe, self._fd, self._td = (np.zeros((n, 3)) for _ in range(3))
        self._hit = np.zeros(n, np.int8)  # particles with a contact in the last force pass
        self._lay = (None, None)  # ((pair arrays it was made from), dem.forces.pair_layout)
        self._wf = np.zeros((len(self.walls), 9))  # wall resultants: total, fe, fd [N]
        self._out = np.empty((0, NOUT))
        self._zeroed = False
        self._elastic, self._spring = self._evaluate(True)
        self._at, self._wf_prev = self._positions(), self._wf.copy()
        if cell is not None and self.nl.builds:
            self._check_cell_overlaps(allow_overlap)
        self._e0 = self.kinetic_energy().sum() + self._elastic
        self._shadow0 = self._shadow()
        self._good = None
        self._check()

    # ---------------------------------------------------------------- forces
    def _layout(self, fresh: bool):
        """`dem.forces.pair_layout` of the current pair list (None in a periodic cell or
        if the list is not sorted by i). Rebuilt when the list or its history arrays are
        new objects; with ``fresh`` its live flags are recomputed from the history (the
        arrays may have been written between two calls of `step`)."""
        nl = self.nl
        key = self._lay[0]
        if key is None or key[0] is not nl.pi or key[1] is not nl.hist or \
                key[2] is not nl.slip or key[3] is not nl.etan:
            lay = None
            if self.cell is None and len(nl.pi) and (len(nl.pi) < 2
                                                     or (nl.pi[1:] >= nl.pi[:-1]).all()):
                lay = pair_layout(nl.pi, nl.pj, self.p.n, nl.hist, nl.slip, nl.etan)
            self._lay = ((nl.pi, nl.hist, nl.slip, nl.etan), lay)
        elif fresh and self._lay[1] is not None:
            refresh_live(nl.hist, nl.slip, nl.etan, self._lay[1][2])
        return self._lay[1]

    def _evaluate(self, update_history: bool, disp2=None, fresh=True):
        """Contact forces now into p.force/p.torque, the private class arrays and the wall
        resultants. Returns (elastic energy, tangential spring energy) [J]. disp2: the
        largest squared displacement since the neighbour build if already known (drift);
        fresh: the contact history may have been changed from outside since the last
        force pass (False only between two steps of one `step` call)."""
        p, nl, w = self.p, self.nl, self.walls
        if nl.needs_rebuild(p.x, w.point, self.cell, disp2):
            nl.build(p.x, p.radius, w.point, w.normal, self.cell)
            self._prune(nl)
            self._check_domain()
        h = [nl.hist, nl.slip, nl.etan, nl.whist, nl.wslip, nl.wetan]
        lay = None
        if update_history:
            lay = self._layout(fresh)
        else:
            h = [a.copy() for a in h]
        acc = (p.force, p.torque, self._fe, self._fd, self._td)
        # after a drift the velocities are half a step behind this pass: the dashpots
        # predict them at its instant (`dem.contact.damping`)
        horizon = 0.5 * self.dt if self._zeroed else 0.0
        if not self._zeroed:
            for a in acc:
                a[:] = 0.0
            self._hit[:] = 0
        self._zeroed = False
        m = max(len(nl.pi), len(nl.wi), 1)
        if self._out.shape[0] < m:
            self._out = np.empty((int(1.2 * m) + 16, NOUT))
        cell = NO_CELL if self.cell is None else self.cell.as_kernel_args(nl.img)
        # the cell's work needs the contacts' rows (the same bits as without them), at every
        # pass: the trapezoid of a step under a velocity gradient uses the pass before
        rows = self.cell is not None and update_history
        e1, s1 = pair_forces(nl.pi, nl.pj, p.x, p.v, p.omega, p.radius, p.mass, p.material,
                             self.table, h[0], h[1], h[2], self.dt, self._out, *acc, cell=cell,
                             hit=self._hit, layout=lay, rows=rows, horizon=horizon)
        if rows:
            self._bf_prev = self._bf
            self._bf, self._bf_mixed = self._stress_sums(len(nl.pi))
        e2, s2 = wall_forces(nl.wi, nl.ww, p.x, p.v, p.omega, p.radius, p.mass, p.material,
                             w.point, w.normal, w.velocity, w.table_columns(len(self.materials)),
                             self.table, h[3], h[4], h[5], self.dt, self._out, *acc, self._wf,
                             hit=self._hit, horizon=horizon)
        w.force[:] = self._wf[:, :3]
        if self._ext is not None:
            rows, f, _ = self._ext
            _add_external(rows, f, p.force, self._hit)
        return e1 + e2, s1 + s2

    def kinds_changed(self) -> None:
        """Call after writing ``p.kind`` from outside (grains held or released): the ledger
        books the ghosts' work over the new set of GHOST rows."""
        self._ghosts = self._ghost_index()
        self._at = self._positions()
        if self.walls.free_only.any() or not self.prescribed_pairs:
            # a released grain meets the free_only walls (and the prescribed rows) its GHOST
            # row was kept from
            self.rebuild_neighbours()

    @property
    def forced(self) -> np.ndarray:
        """(n,) int8 flags of the rows whose forces the kicks read (set by the force pass for
        every particle in contact, and for the rows of `set_external_force`); a step hook
        that adds a force to a row must set its flag, or a grain out of contact keeps the
        force in a row no kick reads (`dem.drag.GroupDrag`)."""
        return self._hit

    def external_force(self):
        """(rows (k,), forces (k, 3) [N]) of `set_external_force` (empty if none)."""
        if self._ext is None:
            return np.zeros(0, np.int64), np.zeros((0, 3))
        return self._ext[0], self._ext[1]

    def set_external_force(self, rows, force) -> None:
        """Apply the constant force ``force`` [N] ((k, 3), or (3,) for every row) to the FREE
        particles ``rows`` (k,) from the next force pass on, beside their contact forces and
        gravity: a surcharge or a membrane pressure on a specimen's boundary grains, a fluid
        drag; it is added to the forces now in the arrays, which the next half-kick uses.
        Its work is booked as ``work_external`` in `energy`. ``rows=None`` removes it.
        Not with a periodic cell (positions wrap)."""
        p = self.p
        if self._ext is not None:   # out of the forces now in the arrays
            p.force[self._ext[0]] -= self._ext[1]
        if rows is None:
            self._ext = None
            return
        rows = np.asarray(rows, np.int64).ravel()
        f = np.broadcast_to(np.asarray(force, float), (len(rows), 3)).copy()
        if self.cell is not None:
            raise ValueError("set_external_force: not in a periodic cell")
        if len(rows) and (rows.min() < 0 or rows.max() >= p.n):
            raise ValueError(f"set_external_force: rows must lie in [0, {p.n}), got "
                             f"{rows.min()}..{rows.max()}")
        # (a count, not np.unique: a fluid sets every grain's force each fluid step)
        if len(rows) and np.bincount(rows, minlength=p.n).max() > 1:
            raise ValueError("set_external_force: rows repeat")
        if (p.kind[rows] != FREE).any():
            raise ValueError("set_external_force: rows must be FREE particles (the others' "
                             "motion is prescribed)")
        if not np.isfinite(f).all():
            raise ValueError("set_external_force: force is not finite")
        if p.dim == 2 and (f[:, 2] != 0).any():
            raise ValueError("set_external_force: force[:, 2] must be 0 for 2D disks")
        self._ext = (rows, f, p.x[rows].copy())
        # into the forces now in the arrays, which the next half-kick uses
        p.force[rows] += f
        self._hit[rows] = 1

    def _stress_sums(self, m):
        """Sums over the touching pairs of b (x) f (3, 3, 3) [N m] for f the contact force
        on i by j, its conservative normal part and its damping part (the rows (m, NOUT) of
        the force pass just done), with b the branch vector from i to j's image now and
        with b as it was at the last force pass (the drift between moved the pair apart by
        dt L b there: the trapezoid of the cell's work needs that b). A particle wrapped
        into the cell since then is unwrapped by the whole cell vectors it jumped."""
        cell, nl, x = self.cell, self.nl, self.p.x
        x0, h0 = (x, cell.h) if self._xh is None else self._xh
        bf, bf0 = np.zeros((3, 3, 3)), np.zeros((3, 3, 3))
        _branch_force_sums(nl.pi, nl.pj, nl.img, self._out[:m], x, cell.h, x0, h0,
                           np.linalg.inv(cell.h), bf, bf0)
        self._xh = (x.copy(), cell.h.copy())
        return bf, bf0

    def rebuild_neighbours(self) -> None:
        """Build the neighbour list now (positions or radii changed from outside by more than
        the skin allows, e.g. grains grown in place); the contact history is carried."""
        self.nl.build(self.p.x, self.p.radius, self.walls.point, self.walls.normal, self.cell)
        self._prune(self.nl)

    def _prune(self, nl):
        """Called after every neighbour build, before the force pass: drops the GHOST rows'
        candidates of ``free_only`` walls; a subclass may drop more (`dem.parallel` drops the
        halo copies' own contacts)."""
        if not self.prescribed_pairs and len(nl.pi):
            k = self._own_kinds()
            nl.keep_pairs((k[nl.pi] == FREE) | (k[nl.pj] == FREE))
        w = self.walls
        if len(nl.wi) and w.free_only.any():
            nl.keep_walls(~(w.free_only[nl.ww] & (self.p.kind[nl.wi] == GHOST)))

    def _own_kinds(self) -> np.ndarray:
        """(n,) the particles' own kinds, by which ``prescribed_pairs = False`` drops pairs
        (a subclass holding copies of other runs' particles gives theirs)."""
        return self.p.kind

    def compute_forces(self, update_history: bool = True):
        """Contact forces at the current state into ``p.force``/``p.torque`` and
        ``walls.force``. Returns (elastic energy [J], tangential spring energy [J], power
        of the damping forces on the FREE particles [W], wall power [W], ghost power [W]).
        ``update_history=False`` leaves the contact history untouched (re-evaluation inside
        a staggered coupling iteration)."""
        e, es = self._evaluate(update_history)
        p, w, g = self.p, self.walls, self._ghosts
        if update_history:
            self._elastic, self._spring = e, es
        self._at = self._positions()  # where the forces now in the arrays were evaluated
        f = p.kind == FREE
        pd = float((self._fd[f] * p.v[f]).sum() + (self._td[f] * p.omega[f]).sum())
        pw = -float((w.force * w.velocity).sum())
        pg = -float((p.force[g] * p.v[g]).sum() + (p.torque[g] * p.omega[g]).sum()) \
            if len(g) else 0.0
        return e, es, pd, pw, pg

    def _positions(self, out=None):
        """(positions of the GHOST rows (into ``out`` if given), wall points) now."""
        g = self._ghosts
        xg = _EMPTY if not len(g) else (self.p.x[g] if out is None else _gather_rows(g, self.p.x, out))
        return xg, (self.walls.point.copy() if len(self.walls) else _EMPTY)

    # ---------------------------------------------------------------- stepping
    def step(self, n: int = 1, hook=None, prescribed=None, decay: float | None = None,
             drag=None):
        """Advance n steps of dt (velocity Verlet), with blow-up and domain checks.

        Between two steps of one call (unless a check falls in between) the second
        half-kick and the next drift run as one pass over the particles (`_kick_drift`:
        the same bits as `_kick` then `_drift`), so a caller that needs to act between
        steps passes ``hook`` rather than calling ``step(1)`` n times: ``hook()`` runs after
        each step's force pass, before its second half-kick (forces new, v still the
        half-step velocity; it may write the rows of particles that are not FREE; ``sim.time``
        and ``sim.nsteps`` still hold the values before the step), and a true return ends the
        call after that step. ``prescribed``: a
        `dem.prescribed.Prescribed` whose motions of GHOST rows are written before each
        step's drift (the same bits as writing them from Python before each of n
        ``step(1)`` calls; ghosts' rotations are booked as dt omega, so a prescribed omega
        is constant over the call). ``decay``: the FREE particles' v and omega are scaled
        by it before each step's drift (mass-proportional damping, `dem.control.relax`), the
        kinetic energy it takes out booked as dissipated and summed in ``damping_removed``.
        ``drag``: a `dem.drag.GroupDrag` applied in every step where a hook would run
        (before ``hook``), in the fused loop too (a hook applying it costs the Python loop:
        +20-35 % a step at 0.5-2k grains). Returns the number of steps done."""
        p, dt, cell = self.p, self.dt, self.cell
        pk = None if prescribed is None else prescribed.pack(int(n), dt, p.kind)
        h = 0.5 * dt
        per, lg, org = (0, _NO_L, _NO_O) if cell is None else \
            (1, cell.velocity_gradient, cell.origin)
        acc = (p.force, p.torque, self._fe, self._fd, self._td)
        prm = (p.mass, p.inertia, p.kind, self.gravity, h)
        ng = len(self._ghosts)
        ghosts = ng > 0
        # two buffers each for the ghosts' force rows and positions: a step's rows and
        # positions are the next step's "before" (no allocation per step)
        rowbuf = [np.empty((ng, 15)), np.empty((ng, 15))] if ghosts else None
        posbuf = [np.empty((ng, 3)), np.empty((ng, 3))] if ghosts else None
        res = np.empty(8)
        kd = _kick_drift_par if p.n >= KD_PARALLEL_MIN and get_num_threads() > 1 else _kick_drift
        n = int(n)
        pending = None  # (works of the old forces, largest squared displacement) of a drift
        gprev = None  # ghost rows of the forces the drift cleared
        fused = hook is None and decay is None and cell is None and self._plain_loop()
        s = 0
        while s < n:
            if fused:  # as many steps as it can in one numba call (`_steps`)
                k, pending, gprev = self._fused(s, n, pending, pk, gprev, drag)
                s += k
                if k and self.nsteps % self.check_every == 0:
                    self._check()
                if s == n:
                    break
                if k and pending is None:
                    continue
                # a neighbour build is due before this step's force pass (its drift
                # pending), or the serial drivers do not apply: the step below
            if pending is None:
                if decay is not None:
                    removed = _damp(p.v, p.omega, p.mass, p.inertia, p.kind, decay)
                    self.damping_removed += removed
                    self._led["dissipated"] += removed
                if pk is not None:
                    _prescribe(s, *pk, p.x, p.v, p.omega)
                if ghosts and gprev is None:  # (else the last step's: the kick keeps forces)
                    gprev = self._ghost_rows(rowbuf[0])
                pending = _drift(p.x, p.v, p.omega, *acc, *prm, dt, per, lg, org,
                                 self._x0_tracked(), self._hit)
            wc0, we0, wd0, d2 = pending
            self.walls.advance(dt)
            if cell is not None:
                cell.advance(dt)
            self._zeroed = True  # the drift cleared the force arrays
            self._wf_prev[:] = self._wf
            e, es = self._evaluate(True, d2 if cell is None else None, s == 0)
            gnow = self._ghost_rows(rowbuf[1] if gprev is rowbuf[0] else rowbuf[0]) if ghosts else None
            if drag is not None:
                drag.apply(self)
            last = hook is not None and bool(hook())
            if len(self._ghosts) != ng:   # the buffers (and the numba gathers) are sized for ng
                raise RuntimeError("Simulation.step: the hook changed the set of GHOST rows; "
                                   "change kinds between step calls")
            # of this force pass (before the next step's motions)
            now = self._positions(posbuf[s % 2] if ghosts else None)
            if last or s == n - 1 or (self.nsteps + 1) % self.check_every == 0 or decay is not None:
                wc1, we1, wd1, wg = _kick(p.v, p.omega, *acc, *prm, self._hit)
                pending = None
            else:
                if pk is not None:  # the next step's motions, before its drift (in kd)
                    _prescribe(s + 1, *pk, p.x, p.v, p.omega)
                kd(p.x, p.v, p.omega, *acc, *prm, dt, per, lg, org, self._x0_tracked(),
                   self._hit, res)
                wc1, we1, wd1, wg = res[0], res[1], res[2], res[3]
                pending = (res[4], res[5], res[6], res[7])
            self._book(wc0 + wc1, we0 + we1, wd0 + wd1, wg, e, es, gprev, gnow, now)
            gprev = gnow
            self.time += dt
            self.nsteps += 1
            if self.nsteps % self.check_every == 0:
                self._check()
            s += 1
            if last:
                n = s
                break
        if self.nsteps % self.check_every:
            self._check()
        return n

    _LOOP_METHODS = ("_evaluate", "_book", "_positions", "_ghost_rows", "_x0_tracked")

    def _plain_loop(self) -> bool:
        """Whether the step loop's methods are this class's (a subclass that changes one of
        them keeps the Python loop: `_steps` does what these do here)."""
        cls = type(self)
        return all(getattr(cls, m) is getattr(Simulation, m) for m in self._LOOP_METHODS)

    def _fused(self, s, n, pending, pk, gprev, drag=None):
        """Steps s, s + 1, ... of a `step` call of n steps in `_steps` (no hook, damping or
        cell: the caller checks), if the serial drivers are the ones `_evaluate` would run.
        pk: the packed prescribed motions or None; gprev: the GHOST rows' forces of the
        last force pass (None: not gathered yet in this call). Returns (steps done, the
        pending drift's values or None, gprev); (0, pending, gprev) if it did not apply."""
        p, nl, w = self.p, self.nl, self.walls
        if nl._x0 is None or nl._x0.shape != p.x.shape or (len(w) and nl._wp0 is None):
            return 0, pending, gprev
        if (p.n >= KD_PARALLEL_MIN or len(nl.pi) >= PARALLEL_MIN
                or len(nl.wi) >= WALL_PARALLEL_MIN) and get_num_threads() > 1:
            return 0, pending, gprev
        lay = self._layout(s == 0)
        if lay is None:
            if len(nl.pi):  # not sorted by i: `pair_forces` takes the plain loop
                return 0, pending, gprev
            lay = (np.zeros(p.n + 1, np.int64), np.zeros(0, np.int32), np.zeros(0, np.int8))
        led = self._led
        st = np.array([self.time, self._elastic, self._spring, 0.0, 0.0, 0.0, 0.0]
                      + [led[k] for k in LED_KEYS])
        if pending is not None:
            st[3:7] = pending
        ist = np.array([self.nsteps, pending is not None, 0, gprev is not None], np.int64)
        ext = self._ext is not None
        erows, ef, ex0 = self._ext if ext else (np.zeros(0, np.int64), _EMPTY, _EMPTY)
        nw = len(w)
        wp_at = np.array(self._at[1], float).reshape(nw, 3) if nw else _EMPTY
        gh = self._ghosts
        ng = len(gh)
        gbuf = np.empty((ng, 15)) if gprev is None else np.array(gprev)
        xg_at = np.array(self._at[0], float).reshape(ng, 3)
        _steps(s, n, self.check_every, p.x, p.v, p.omega, p.force, p.torque, self._fe,
               self._fd, self._td, p.mass, p.inertia, p.kind, self.gravity, 0.5 * self.dt,
               self.dt, nl._x0, self._hit, p.radius, p.material, self.table, lay[0], lay[1],
               lay[2], nl.hist, nl.slip, nl.etan, nl.wi, nl.ww, w.point, w.normal,
               w.velocity, w.table_columns(len(self.materials)), nl.whist, nl.wslip,
               nl.wetan, self._wf, self._wf_prev, wp_at, w.force,
               nl._wp0 if nw else _EMPTY, nl.skin, ext, erows, ef, ex0,
               *(_NO_DRAG if drag is None else (True, *drag.arrays(self))), pk is not None,
               *(_NO_PK if pk is None else pk), gh, gbuf, np.empty((ng, 15)), xg_at,
               np.empty((ng, 3)), st, ist)
        done = int(ist[2])
        self.time, self.nsteps = float(st[0]), int(ist[0])
        for q, k in enumerate(LED_KEYS):
            led[k] = float(st[7 + q])
        if done:
            self._elastic, self._spring = float(st[1]), float(st[2])
            self._at = (xg_at if ng else self._at[0], wp_at if nw else self._at[1])
            self._zeroed = False
        return (done, tuple(float(a) for a in st[3:7]) if ist[1] else None,
                gbuf if ist[3] else None)

    def _x0_tracked(self):
        """Build positions of the neighbour list for the drift to measure displacements
        from (empty: not measured, in a periodic cell or before the first build)."""
        x0 = self.nl._x0
        if self.cell is not None or x0 is None or x0.shape != self.p.x.shape:
            return _EMPTY
        return x0

    def _ghost_rows(self, out):
        """(ng, 15) force, torque, fe, fd, td of the GHOST particles now, into ``out``."""
        p = self.p
        return _gather_ghosts(self._ghosts, p.force, p.torque, self._fe, self._fd, self._td, out)

    def _book(self, wc, we, wd, wg, e, es, gprev, gnow, now):
        """Energy ledger of one step, every term by the trapezoidal rule over the actual
        displacements: free particles (from the drift and the kick), ghosts (their force
        rows ``gprev`` at the drift and ``gnow`` after the force pass) and walls (positions
        ``now`` at this force pass and those at the last). Contact work that is neither
        conservative normal work nor spring energy is dissipated; the damping part is the
        work of the dashpots. (A ghost's rotation is dt omega now: a prescribed omega is
        constant over a `step` call.)"""
        led, p, g = self._led, self.p, self._ghosts
        (xg0, wp0), (xg1, wp1) = self._at, now
        self._at = (xg1, wp1)
        wgh = wge = wgd = 0.0  # work of the contacts on the ghosts (all, fe, fd)
        if len(g):
            wgh, wge, wgd = _ghost_work(gprev, gnow, xg0, xg1, p.omega, g, self.dt)
        www = wwe = wwd = 0.0  # work of the contacts on the walls (all, fe, fd)
        if len(self.walls):
            www, wwe, wwd = _wall_work(self._wf_prev, self._wf, wp0, wp1)
        wcell = np.zeros(3)  # work of the cell on the contacts (all, fe, fd)
        if self.cell is not None:
            # the contacts' share of the affine motion (f . L b dt a pair), trapezoidal
            lt = self.cell.velocity_gradient.T
            wcell = 0.5 * self.dt * ((self._bf_prev + self._bf_mixed) * lt).sum(axis=(1, 2))
        contact = wc + wgh + www - wcell[0]
        if self._ext is not None:   # wc holds the external forces' work too: book it apart
            rows, f, x0 = self._ext
            wext = _external_work(rows, f, p.x, x0)
            contact -= wext
            led["external"] += wext
        dissipated = -(contact - (we + wge + wwe - wcell[1])) - (es - self._spring)
        damping = -(wd + wgd + wwd - wcell[2])
        led["dissipated"] += dissipated
        led["friction"] += dissipated - damping
        led["walls"] -= www
        led["ghosts"] -= wgh
        led["gravity"] += wg
        led["cell"] += wcell[0]
        self._elastic, self._spring = e, es
    def _branches(self):
        """Branch vectors (m, 3) [m] from i to (the nearest image of) j of the listed pairs."""
        p, nl = self.p, self.nl
        d = p.x[nl.pj] - p.x[nl.pi]
        if self.cell is not None:
            d += nl.img @ self.cell.h.T
        return d

    def contact_forces(self, skip_ghost_pairs: bool = True, return_branch: bool = False):
        """Touching pairs (m, 2) and the force on i by j (m, 3) [N] now (and, if
        ``return_branch``, the branch vectors (m, 3) [m] from i to j's image).

        The pair loop is evaluated again on copies of the contact history (the run keeps
        no per-contact forces), so calling this changes nothing. Pairs of two GHOST
        particles (a rigid clump's own contacts) are left out by default.
        """
        p, nl = self.p, self.nl
        out = np.zeros((max(len(nl.pi), 1), NOUT))
        scratch = [np.zeros_like(p.force) for _ in range(5)]
        cell = NO_CELL if self.cell is None else self.cell.as_kernel_args(nl.img)
        pair_forces(nl.pi, nl.pj, p.x, p.v, p.omega, p.radius, p.mass, p.material, self.table,
                    nl.hist.copy(), nl.slip.copy(), nl.etan.copy(), self.dt, out, *scratch,
                    cell=cell, rows=True)
        b = self._branches()
        keep = np.linalg.norm(b, axis=1) < p.radius[nl.pi] + p.radius[nl.pj]
        if skip_ghost_pairs:
            keep &= ~((p.kind[nl.pi] == GHOST) & (p.kind[nl.pj] == GHOST))
        res = np.stack([nl.pi[keep], nl.pj[keep]], axis=1), -out[: len(nl.pi)][keep, :3]
        return res + (b[keep],) if return_branch else res

    # ---------------------------------------------------------------- state
    def state_dict(self) -> dict:
        """Everything a run continues from, bit for bit, as a flat dict of copies (numpy
        arrays and Python scalars; ``np.savez``-ready): particles (``particles.*``: x, v,
        omega, force, torque, radius, mass, inertia, material, kind, dim), the force
        parts of the last force pass the next drift books (``integrator.*``), time, step
        count, dt and gravity, the ledger's sums (``ledger.*``), the walls' state
        (``walls.*``), the neighbour list with its contact history and build positions
        (``contacts.*``, `dem.neighbours.NeighbourList.state_dict`) and the periodic cell
        (``cell.*``) if any. `load_state` restores it into a Simulation built the same way."""
        d = {f"particles.{k}": v for k, v in self.p.state_dict().items()}
        d["particles.dim"] = int(self.p.dim)
        d.update(time=float(self.time), nsteps=int(self.nsteps), dt=float(self.dt),
                 gravity=self.gravity.copy())
        (xg, wp) = self._at
        d.update({"integrator.fe": self._fe.copy(), "integrator.fd": self._fd.copy(),
                  "integrator.td": self._td.copy(), "integrator.hit": self._hit.copy(),
                  "integrator.wall_resultants": self._wf.copy(),
                  "integrator.wall_resultants_prev": self._wf_prev.copy(),
                  "integrator.at_ghosts": np.array(xg), "integrator.at_walls": np.array(wp),
                  "integrator.zeroed": bool(self._zeroed)})
        d.update({f"ledger.{k}": float(v) for k, v in self._led.items()})
        d.update({"ledger.elastic": float(self._elastic), "ledger.spring": float(self._spring),
                  "ledger.initial": float(self._e0), "ledger.initial_shadow": float(self._shadow0)})
        d.update({f"walls.{k}": v for k, v in self.walls.state_dict().items()})
        d.update({f"contacts.{k}": v for k, v in self.nl.state_dict().items()})
        if self.cell is not None:
            d.update({f"cell.{k}": v for k, v in self.cell.state_dict().items()})
            d.update({"cell.bf": self._bf.copy(), "cell.bf_prev": self._bf_prev.copy(),
                      "cell.bf_mixed": self._bf_mixed.copy()})
            if self._xh is not None:
                d.update({"cell.xh_x": self._xh[0].copy(), "cell.xh_h": self._xh[1].copy()})
        return d

    def load_state(self, d) -> None:
        """Restore a `state_dict` (a dict or an ``np.load`` of one) into this Simulation,
        built the same way (particle count, walls, cell). Raises ValueError naming the key
        of a missing entry, an unknown one, or one whose shape does not fit."""
        d = dict(d)
        want = set(self.state_dict())  # the keys of this configuration (cheap: copies)
        # ledger.external: absent from states written before external forces existed
        optional = {"cell.xh_x", "cell.xh_h", "ledger.external"}
        for k in sorted(want - optional):
            if k not in d:
                raise ValueError(f"state has no {k!r} (a state_dict of another configuration?)")
        for k in sorted(d):
            if k not in want | optional:
                raise ValueError(f"state key {k!r} is unknown to this Simulation (a state_dict "
                                 f"of another configuration: cell, walls?)")
        p = self.p
        if int(d["particles.dim"]) != p.dim:
            raise ValueError(f"state 'particles.dim' is {int(d['particles.dim'])}, this "
                             f"Simulation's particles are {p.dim}D")
        fixed = {f"particles.{k}": getattr(p, k) for k in _STATE_KEYS}
        fixed.update({"integrator.fe": self._fe, "integrator.fd": self._fd,
                      "integrator.td": self._td, "integrator.hit": self._hit,
                      "integrator.wall_resultants": self._wf,
                      "integrator.wall_resultants_prev": self._wf_prev,
                      "gravity": self.gravity})
        for k, a in fixed.items():
            _fit(k, d[k], a.shape)
        self.walls.load_state(_section(d, "walls."))
        self.nl.load_state(_section(d, "contacts."))
        for k, a in fixed.items():
            a[...] = np.asarray(d[k], a.dtype)
        self.time, self.nsteps, self.dt = float(d["time"]), int(d["nsteps"]), float(d["dt"])
        ng = len(self._ghost_index())
        xg = _fit("integrator.at_ghosts", d["integrator.at_ghosts"], (ng, 3) if ng else None)
        wp = _fit("integrator.at_walls", d["integrator.at_walls"],
                  (len(self.walls), 3) if len(self.walls) else None)
        self._at = (np.array(xg, float).reshape(-1, 3), np.array(wp, float).reshape(-1, 3))
        self._zeroed = bool(d["integrator.zeroed"])
        for k in self._led:
            self._led[k] = float(d.get(f"ledger.{k}", 0.0))
        self._elastic, self._spring = float(d["ledger.elastic"]), float(d["ledger.spring"])
        self._e0, self._shadow0 = float(d["ledger.initial"]), float(d["ledger.initial_shadow"])
        if self.cell is not None:
            self.cell.load_state(_section(d, "cell.", exclude=("bf", "bf_prev", "bf_mixed",
                                                              "xh_x", "xh_h")))
            self._bf, self._bf_prev, self._bf_mixed = (
                np.array(_fit(f"cell.{k}", d[f"cell.{k}"], (3, 3, 3)), float)
                for k in ("bf", "bf_prev", "bf_mixed"))
            self._xh = (np.array(d["cell.xh_x"], float), np.array(d["cell.xh_h"], float)) \
                if "cell.xh_x" in d else None
        self._ghosts = self._ghost_index()
        self._lay = (None, None)  # the pair layout is rebuilt from the history restored
        self._good = None
        if self._ext is not None:
            self._ext[2][:] = p.x[self._ext[0]]
        self._check()

    def ledger(self) -> dict:
        """The ledger's stored terms [J] (what `energy` combines; `state_dict` holds them
        too): sums over the steps so far of the contact work that was dissipated
        (``dissipated``; ``friction`` its non-damping part) and of the work of the walls
        (``walls``), the ghosts (``ghosts``), gravity (``gravity``) and the periodic cell
        (``cell``) on the particles; the ``elastic`` energy (normal + springs) and the
        ``spring`` energy of the last force pass; ``initial`` (kinetic + elastic) and
        ``initial_shadow`` at the start. `shadow_energy` gives the shadow term now."""
        return dict(self._led, elastic=float(self._elastic), spring=float(self._spring),
                    initial=float(self._e0), initial_shadow=float(self._shadow0))

    def shadow_energy(self) -> float:
        """Sum dt^2/(8m) |F + m g|^2 + dt^2/(8I) |T|^2 over FREE particles now [J] (the
        velocity Verlet term of `energy`)."""
        return self._shadow()

    def force_parts(self):
        """(fe, fd, td) (n, 3) [N, N, N m]: the conservative normal and the damping parts of
        ``p.force`` and the damping part of ``p.torque`` from the last force pass (views;
        the next drift books their work: a caller that carries forces over writes them)."""
        return self._fe, self._fd, self._td

    def wall_resultants(self) -> np.ndarray:
        """(nw, 9) resultants of the particles on each wall at the last force pass [N]:
        total, conservative normal and damping part (a view; the next step books the walls'
        work from them)."""
        return self._wf

    def history_replaced(self) -> None:
        """Call after writing the contact history (``nl.hist/slip/etan`` and the wall
        ones) from outside: the stored elastic energy takes the new springs' energy (its
        normal part depends on the positions only)."""
        normal = self._elastic - self._spring
        self._spring = float(self.nl.etan.sum() + self.nl.wetan.sum())
        self._elastic = normal + self._spring

    def _ghost_index(self):
        """Rows whose contact work is booked as the ghosts' (a subclass may leave some out)."""
        return np.flatnonzero(self.p.kind == GHOST)

    # ---------------------------------------------------------------- energy ledger
    def kinetic_energy(self) -> np.ndarray:
        """(translational, rotational) kinetic energy of FREE particles [J] (in a periodic
        cell: of the velocity fluctuations)."""
        p, f = self.p, self.p.kind == FREE
        return np.array([0.5 * (p.mass[f] * (p.v[f] ** 2).sum(1)).sum(),
                         0.5 * (p.inertia[f] * (p.omega[f] ** 2).sum(1)).sum()])

    def _shadow(self) -> float:
        """Sum dt^2/(8m) |F + m g|^2 + dt^2/(8I) |T|^2 over FREE particles [J]: K minus
        this is what velocity Verlet changes by exactly the trapezoidal work."""
        p, f = self.p, self.p.kind == FREE
        ft = p.force[f] + p.mass[f, None] * self.gravity
        c = 0.125 * self.dt**2
        return c * float(((ft**2).sum(1) / p.mass[f]).sum()
                         + ((p.torque[f] ** 2).sum(1) / p.inertia[f]).sum())

    def energy(self) -> dict:
        """Energy ledger [J] of the FREE particles.

        Keys: kinetic (translational, rotational), elastic (normal contact energy plus the
        tangential springs), dissipated_damping (work of the normal dashpots, clipping and
        the tangential dashpots while sticking), dissipated_friction (the rest of the
        contact work that is not stored elastically: Coulomb sliding, rolling resistance,
        spring energy lost on sliding, opening and stiffness changes), work_gravity,
        work_walls, work_ghosts, work_external (`set_external_force`) (work done on the
        particles), work_cell (in a deforming
        periodic cell: the work of the affine motion on the contacts, sum f . L b dt over
        the pairs = V sigma : L dt a step, sigma the Love-Weber stress; 0 without a cell), shadow
        (sum dt^2/(8m)|F|^2 + dt^2/(8I)|T|^2, the velocity Verlet term), initial (kinetic +
        elastic at the start) and ``balance`` = kinetic - shadow + elastic + dissipated -
        work - (initial - initial shadow). Every work is taken by the trapezoidal rule over
        the actual displacements, for which velocity Verlet closes the kinetic part
        exactly: the balance is the time error of the conservative normal forces only
        (the cell's work is the trapezoid (f_old + f_new)/2 . L b_old dt a pair, b_old the
        branch vector the drift moved by, exact like the rest for linear forces)."""
        kt, kr = self.kinetic_energy()
        led = self._led
        sh = self._shadow()
        stored = kt + kr - sh + self._elastic + led["dissipated"]
        work = led["gravity"] + led["walls"] + led["ghosts"] + led["cell"] + led["external"]
        return dict(kinetic_translational=kt, kinetic_rotational=kr, elastic=self._elastic,
                    dissipated_damping=led["dissipated"] - led["friction"],
                    dissipated_friction=led["friction"],
                    work_gravity=led["gravity"], work_walls=led["walls"],
                    work_ghosts=led["ghosts"], work_cell=led["cell"],
                    work_external=led["external"], shadow=sh,
                    initial=self._e0,
                    balance=stored - work - (self._e0 - self._shadow0))

    def _check_cell_overlaps(self, allow: bool):
        b = self._branches()
        ov = self.p.radius[self.nl.pi] + self.p.radius[self.nl.pj] - np.linalg.norm(b, axis=1)
        if not allow and len(ov) and ov.max() > 0:
            k = int(np.argmax(ov))
            raise OverlapError(f"{int((ov > 0).sum())} overlapping particle pairs at the start "
                               f"(through the periodic faces too); the largest overlap is "
                               f"{ov[k]:.6g} m between particles "
                               f"{(int(self.nl.pi[k]), int(self.nl.pj[k]))} (pass "
                               f"allow_overlap=True to accept)")

    # ---------------------------------------------------------------- checks
    def _check_domain(self):
        if self.domain is None:
            return
        lo, hi = self.domain
        f = self.p.kind == FREE
        out = f & ((self.p.x < lo) | (self.p.x > hi)).any(axis=1)
        if out.any():
            i = int(np.flatnonzero(out)[0])
            raise DomainError(f"particle {i} left the domain box {lo.tolist()}..{hi.tolist()}"
                              f" at x = {self.p.x[i].tolist()} (t = {self.time:.6g} s, step "
                              f"{self.nsteps}; {int(out.sum())} particles outside)")

    def _check(self):
        p, led = self.p, self._led
        ke, ok = _kinetic_finite(p.x, p.v, p.omega, p.mass, p.inertia, p.kind)
        if ok:
            budget = (self._e0 + abs(led["gravity"]) + abs(led["walls"]) + abs(led["ghosts"])
                      + abs(led["cell"]) + abs(led["external"]))
            ok = ke <= self.blowup_factor * budget + 1e-300
        if not ok:
            why = "NaN in x, v or omega" if not np.isfinite(p.v).all() else "kinetic energy jump"
            if self._good is not None:
                np.savez(self.state_path, **self._good)
            raise BlowUpError(f"blow-up ({why}) at step {self.nsteps}, t = {self.time:.6g} s "
                              f"(dt = {self.dt:.4g} s); last good state written to "
                              f"{self.state_path}", self.state_path)
        self._check_domain()
        g = self._good
        if g is None or g["x"].shape != p.x.shape:
            self._good = dict(p.state_dict(), time=self.time, step=self.nsteps)
        else:  # into the same buffers (no fresh pages to fault in at every check)
            for k in _STATE_KEYS:
                np.copyto(g[k], getattr(p, k))
            g["dim"], g["time"], g["step"] = np.int64(p.dim), self.time, self.nsteps

    def contacts(self):
        """(i, j) (k,) int64 of touching particle pairs now."""
        nl, r = self.nl, self.p.radius
        t = np.linalg.norm(self._branches(), axis=1) < r[nl.pi] + r[nl.pj]
        return nl.pi[t], nl.pj[t]
