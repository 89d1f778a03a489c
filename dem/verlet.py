"""Velocity Verlet kernels with rotations: the half-kicks, the drift, their fused pass, damping.

One step (half-kick / drift / force / half-kick): v += dt/2 a, w += dt/2 T/I; x += dt v;
forces at the new positions; v += dt/2 a, w += dt/2 T/I. Only FREE particles move (kind
0); GHOST and FIXED rows keep what is written into them. Gravity enters the acceleration,
not ``force``. Each kernel books its half of the trapezoidal work of the contact forces
over the step's displacement (`dem.ledger` adds the rest); `dem.integrate.Simulation` runs
them (`dem.fused_steps` too, between neighbour builds).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from dem.forces import spread

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
