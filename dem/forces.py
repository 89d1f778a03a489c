"""The one cached pair loop: particle-particle and particle-wall contact forces.

Each contact's kinematics is computed once (`dem.contact.kinematics`), the law is picked by
its integer id (``apply_law``: an integer switch, not a function argument, so numba's disk
cache works). Two drivers share the per-contact code:

- rows: per-contact results go to rows of ``out`` in a ``prange`` loop, then a serial
  scatter (or, over the compact layout, a parallel per-particle `_gather` that visits
  only particles with a touching contact) sums them onto particles in contact order
  (used from ``PARALLEL_MIN`` candidate pairs on when numba runs more than one thread,
  and whenever the caller wants the rows); wall contacts likewise (`_wall_rows`, then a
  serial scatter in candidate order) from ``WALL_PARALLEL_MIN`` candidates on;
- fused: one serial loop that resolves a contact on scalars (`_resolve`) and adds it to
  its two particles at once (no row array in memory at all).

Most candidate pairs of a Verlet list are open: a sqrt-free pre-test
(``d^2 > (r_i + r_j)^2 (1 + 1e-12)``, which implies delta <= 0 whatever the rounding)
releases them before their kinematics and parameter row are touched; walls use the exact
open test `wall_delta` up front. Without a cell the integrator passes a compact
layout of the list (`pair_layout`: offsets per particle, int32 partners, live flags) so
that an open candidate with no history costs a 4-byte index and one flag.

Both add the same numbers in the same order, so results do not depend on the driver, the
thread count or scheduling.

Row layout of ``out`` (NOUT = 23): force on j [N] (0:3), torque on i (3:6) and on j
(6:9) [N m]; their damping parts (normal dashpot and clipping, tangential dashpot while
sticking): force on j (9:12), torque on i (12:15), on j (15:18); elastic energy [J] (18,
> 0 iff touching; rows of open contacts are only valid there); the conservative normal
force on j (19:22) [N]; tangential spring energy [J] (22). The rest of the contact force
(Coulomb sliding, rolling resistance, the tangential spring) is "friction": its energy
is booked by the integrator as the work it actually does minus the change of the spring
energy (`dem.ledger`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import get_num_threads, njit, prange

from dem.contact import H_CLAIM, H_FN, H_VN, HIST, P_LAW, P_MUR
from dem.contact.hertz_mindlin import hertz_mindlin_law
from dem.contact.kinematics import contact_kinematics, project_history, wall_contact_kinematics, wall_delta
from dem.contact.linear import linear_law

NOUT = 23
PARALLEL_MIN = 4096
"""Candidate pairs from which, with more than one numba thread, the ``prange`` drivers run
(rows in chunks spread over the threads, then `_gather`). Settle scene (benchmarks/
dem_throughput.py), 2 threads on the 2-vCPU machine: see its results.json. The results are
the same bits whatever the driver and the thread count."""

__all__ = ["NOUT", "PARALLEL_MIN", "apply_law", "pair_forces", "pair_layout", "refresh_live",
           "wall_forces"]

_NOHIT = np.zeros(0, np.int8)


def _check_history(hist, m, who):
    """The kernels read HIST columns of m rows (numba does not check bounds)."""
    if hist.ndim != 2 or hist.shape[0] < m or hist.shape[1] != HIST:
        raise ValueError(f"{who}: the contact history must have shape ({m}, {HIST}) "
                         f"(`dem.contact.HIST`), got {hist.shape}")


NO_CELL = (0, np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((0, 3)))
"""(periodic flag, h, velocity gradient, image shifts) of a simulation without a cell."""


@njit(cache=True, inline="always")
def _release(k, hist, slip, etan):
    """An open contact k: a loaded spring is released, the last normal force forgotten."""
    if etan[k] != 0.0 or slip[k] != 0 or hist[k, 0] != 0.0 or hist[k, 1] != 0.0 \
            or hist[k, 2] != 0.0 or hist[k, H_FN] != 0.0:
        hist[k, 0] = hist[k, 1] = hist[k, 2] = 0.0
        hist[k, H_FN] = hist[k, H_VN] = hist[k, H_CLAIM] = 0.0
        slip[k] = 0
        etan[k] = 0.0


# The per-contact code is split by what it touches. Helpers that take arrays are straight
# loads or stores (`_params`, `_kin_ij`, `_kin_wall`, `_history`, `_put_history`,
# `_put_row`, `_row`, `_add_i`, `_add_j`, `_add_wall`); those that branch (`_resolve`, the
# laws, the kinematics of `dem.contact.kinematics`) take scalars only. An array passed into
# an inlined helper costs numba an atomic reference count at its entry and exit, which its
# reference count pruning removes only when no branch lies between them: the pair loops
# that passed arrays (and a parameter-row view) into a branching per-contact helper did
# about 20 such counts per touching contact and ran 1.8-2.5x slower on dense packings
# (pair pass alone; tests/dem/test_dense_paths.py checks the drivers agree to the bit).


@njit(cache=True, inline="always")
def apply_law(law, prm, delta, reff, meff, vn, vtx, vty, vtz, sx, sy, sz, slip, dt, fo, vo,
              co, h):
    """Law registry: id -> law function (ids in `dem.contact.LAWS`); prm: the parameter
    scalars of `_params`."""
    _, es, gs, beta, mus, mud, kn, kt, _, clip = prm
    if law == 0:
        return linear_law(kn, kt, beta, mus, mud, clip, delta, reff, meff, vn, vtx, vty, vtz,
                          sx, sy, sz, slip, dt, fo, vo, co, h)
    return hertz_mindlin_law(es, gs, beta, mus, mud, clip, delta, reff, meff, vn, vtx, vty,
                             vtz, sx, sy, sz, slip, dt, fo, vo, co, h)


@njit(cache=True, inline="always")
def _params(table, a, b):
    """Pair parameter row of materials a, b as NPARAM scalars (P_* order), read element by
    element: a row view ``table[a, b]`` would be reference counted."""
    return (table[a, b, 0], table[a, b, 1], table[a, b, 2], table[a, b, 3], table[a, b, 4],
            table[a, b, 5], table[a, b, 6], table[a, b, 7], table[a, b, 8], table[a, b, 9])


@njit(cache=True, inline="always")
def _resolve(kin, prm, sx, sy, sz, slip, fo, vo, co, wrx, wry, wrz, dt, h):
    """One contact with overlap kin[3] > 0, on scalars only. kin: `pair_kinematics`; prm:
    `_params`; s, slip, fo, vo, co: the spring [m], slip flag, normal force [N], speed
    [m/s] and release claim of its history; wr = omega_i - omega_j [rad/s] (rolling); h:
    the dashpot's prediction horizon [s] (`dem.contact.damping`). Returns 30 values: the
    NOUT values of its row (layout in the module docstring), then the new spring (3), slip
    flag, normal force, normal speed and release claim."""
    nx, ny, nz, delta, reff, meff, vn, vtx, vty, vtz, ai, aj = kin
    sx, sy, sz = project_history(sx, sy, sz, nx, ny, nz)
    fn, fnd, ftx, fty, ftz, fdx, fdy, fdz, sx, sy, sz, sl, e_n, e_pre, e_t, p_fric, claim = \
        apply_law(int(prm[P_LAW]), prm, delta, reff, meff, vn, vtx, vty, vtz, sx, sy, sz,
                  slip, dt, fo, vo, co, h)
    # torques -a n x f on i and j of the tangential force and of its damping part
    cx = ny * ftz - nz * fty
    cy = nz * ftx - nx * ftz
    cz = nx * fty - ny * ftx
    tix, tiy, tiz = -ai * cx, -ai * cy, -ai * cz
    tjx, tjy, tjz = -aj * cx, -aj * cy, -aj * cz
    mur = prm[P_MUR]
    if mur > 0.0:
        w = math.sqrt(wrx * wrx + wry * wry + wrz * wrz)
        if w > 0.0:
            mr = mur * abs(fn) * reff / w  # constant rolling torque against the relative spin
            tix -= mr * wrx
            tiy -= mr * wry
            tiz -= mr * wrz
            tjx += mr * wrx
            tjy += mr * wry
            tjz += mr * wrz
    gx = ny * fdz - nz * fdy
    gy = nz * fdx - nx * fdz
    gz = nx * fdy - ny * fdx
    fe = fn - fnd
    return (fn * nx + ftx, fn * ny + fty, fn * nz + ftz, tix, tiy, tiz, tjx, tjy, tjz,
            fnd * nx + fdx, fnd * ny + fdy, fnd * nz + fdz, -ai * gx, -ai * gy, -ai * gz,
            -aj * gx, -aj * gy, -aj * gz, e_n + e_t, fe * nx, fe * ny, fe * nz, e_t,
            sx, sy, sz, sl, fn, vn, claim)


@njit(cache=True, inline="always")
def _kin_ij(x, v, omega, radius, mass, i, j, dx, dy, dz, d, delta, ux, uy, uz):
    """`pair_kinematics` of a pair whose caller has the branch d = (dx, dy, dz), its length
    and the overlap delta > 0 (ux: the image velocity of a periodic cell, else 0)."""
    return contact_kinematics(dx, dy, dz, d, delta, radius[i], radius[j], mass[i], mass[j],
                              v[i, 0], v[i, 1], v[i, 2], v[j, 0] + ux, v[j, 1] + uy,
                              v[j, 2] + uz, omega[i, 0], omega[i, 1], omega[i, 2],
                              omega[j, 0], omega[j, 1], omega[j, 2])


@njit(cache=True, inline="always")
def _kin_wall(x, v, omega, radius, mass, i, wall_n, wall_u, w, delta):
    """`wall_kinematics` of particle i touching wall w (overlap delta > 0)."""
    return wall_contact_kinematics(delta, radius[i], mass[i], wall_n[w, 0], wall_n[w, 1],
                                   wall_n[w, 2], v[i, 0], v[i, 1], v[i, 2], wall_u[w, 0],
                                   wall_u[w, 1], wall_u[w, 2], omega[i, 0], omega[i, 1],
                                   omega[i, 2])


@njit(cache=True, inline="always")
def _history(k, hist, slip):
    """(sx, sy, sz, slip, fn, vn, claim) of contact k."""
    return (hist[k, 0], hist[k, 1], hist[k, 2], slip[k], hist[k, H_FN], hist[k, H_VN],
            hist[k, H_CLAIM])


@njit(cache=True, inline="always")
def _put_history(k, r, hist, slip, etan):
    """Store the new history of contact k from the values r of `_resolve`."""
    hist[k, 0] = r[23]
    hist[k, 1] = r[24]
    hist[k, 2] = r[25]
    hist[k, H_FN] = r[27]
    hist[k, H_VN] = r[28]
    hist[k, H_CLAIM] = r[29]
    slip[k] = r[26]
    etan[k] = r[22]


@njit(cache=True, inline="always")
def _put_row(out, k, r):
    """Row k of out (NOUT) from the values r of `_resolve`."""
    out[k, 0], out[k, 1], out[k, 2], out[k, 3], out[k, 4], out[k, 5] = r[:6]
    out[k, 6], out[k, 7], out[k, 8], out[k, 9], out[k, 10], out[k, 11] = r[6:12]
    out[k, 12], out[k, 13], out[k, 14], out[k, 15], out[k, 16], out[k, 17] = r[12:18]
    out[k, 18], out[k, 19], out[k, 20], out[k, 21], out[k, 22] = r[18:23]


@njit(cache=True, inline="always")
def _row(out, k):
    """Row k of out as the first NOUT values of a `_resolve` result."""
    return (out[k, 0], out[k, 1], out[k, 2], out[k, 3], out[k, 4], out[k, 5], out[k, 6],
            out[k, 7], out[k, 8], out[k, 9], out[k, 10], out[k, 11], out[k, 12], out[k, 13],
            out[k, 14], out[k, 15], out[k, 16], out[k, 17], out[k, 18], out[k, 19],
            out[k, 20], out[k, 21], out[k, 22])


@njit(cache=True, inline="always")
def _add_i(i, r, force, torque, fe, fd, td):
    """Add the contact values r (`_resolve`, `_row`) to particle i."""
    force[i, 0] -= r[0]
    force[i, 1] -= r[1]
    force[i, 2] -= r[2]
    torque[i, 0] += r[3]
    torque[i, 1] += r[4]
    torque[i, 2] += r[5]
    fe[i, 0] -= r[19]
    fe[i, 1] -= r[20]
    fe[i, 2] -= r[21]
    fd[i, 0] -= r[9]
    fd[i, 1] -= r[10]
    fd[i, 2] -= r[11]
    td[i, 0] += r[12]
    td[i, 1] += r[13]
    td[i, 2] += r[14]


@njit(cache=True, inline="always")
def _add_j(j, r, force, torque, fe, fd, td):
    """Add the contact values r (`_resolve`, `_row`) to particle j."""
    force[j, 0] += r[0]
    force[j, 1] += r[1]
    force[j, 2] += r[2]
    torque[j, 0] += r[6]
    torque[j, 1] += r[7]
    torque[j, 2] += r[8]
    fe[j, 0] += r[19]
    fe[j, 1] += r[20]
    fe[j, 2] += r[21]
    fd[j, 0] += r[9]
    fd[j, 1] += r[10]
    fd[j, 2] += r[11]
    td[j, 0] += r[15]
    td[j, 1] += r[16]
    td[j, 2] += r[17]


@njit(cache=True, inline="always")
def _add_wall(w, r, wall_f):
    """Add the contact values r to the resultants of wall w (the row's "particle j")."""
    wall_f[w, 0] += r[0]
    wall_f[w, 1] += r[1]
    wall_f[w, 2] += r[2]
    wall_f[w, 3] += r[19]
    wall_f[w, 4] += r[20]
    wall_f[w, 5] += r[21]
    wall_f[w, 6] += r[9]
    wall_f[w, 7] += r[10]
    wall_f[w, 8] += r[11]


_SURE_OPEN = 1.0 + 1e-12
"""d^2 > (r_i + r_j)^2 x this: the pair is open whatever the rounding of d = sqrt(d^2)."""


@njit(cache=True, inline="always")
def _image(x, h, img, i, j, k):
    """Branch from i to the image x_j + h img[k] of j [m] (periodic cells)."""
    ix = img[k, 0]
    iy = img[k, 1]
    iz = img[k, 2]
    return (x[j, 0] - x[i, 0] + h[0, 0] * ix + h[0, 1] * iy + h[0, 2] * iz,
            x[j, 1] - x[i, 1] + h[1, 0] * ix + h[1, 1] * iy + h[1, 2] * iz,
            x[j, 2] - x[i, 2] + h[2, 0] * ix + h[2, 1] * iy + h[2, 2] * iz)


@njit(cache=True, inline="always")
def _image_velocity(lg, dx, dy, dz):
    """Velocity L d of j's image relative to i beyond v_j - v_i [m/s]."""
    return (lg[0, 0] * dx + lg[0, 1] * dy + lg[0, 2] * dz,
            lg[1, 0] * dx + lg[1, 1] * dy + lg[1, 2] * dz,
            lg[2, 0] * dx + lg[2, 1] * dy + lg[2, 2] * dz)


@njit(cache=True)
def _pair_rows_range(lo, hi, pi, pj, x, v, omega, radius, mass, material, table, hist, slip,
                     etan, dt, hp, per, h, lg, img, out):
    """Rows lo:hi of `_pair_rows` (open rows: only column 18, = 0)."""
    for k in range(lo, hi):
        i = pi[k]
        j = pj[k]
        if per:
            dx, dy, dz = _image(x, h, img, i, j, k)
            ux, uy, uz = _image_velocity(lg, dx, dy, dz)
        else:
            dx = x[j, 0] - x[i, 0]
            dy = x[j, 1] - x[i, 1]
            dz = x[j, 2] - x[i, 2]
            ux = uy = uz = 0.0
        rs = radius[i] + radius[j]
        d2 = dx * dx + dy * dy + dz * dz
        if d2 > rs * rs * _SURE_OPEN:
            out[k, 18] = 0.0
            _release(k, hist, slip, etan)
            continue
        d = math.sqrt(d2)
        delta = rs - d
        if delta <= 0.0:
            out[k, 18] = 0.0
            _release(k, hist, slip, etan)
            continue
        kin = _kin_ij(x, v, omega, radius, mass, i, j, dx, dy, dz, d, delta, ux, uy, uz)
        sx, sy, sz, sl, fo, vo, co = _history(k, hist, slip)
        r = _resolve(kin, _params(table, material[i], material[j]), sx, sy, sz, sl, fo, vo, co,
                     omega[i, 0] - omega[j, 0], omega[i, 1] - omega[j, 1],
                     omega[i, 2] - omega[j, 2], dt, hp)
        _put_history(k, r, hist, slip, etan)
        _put_row(out, k, r)


PAIR_CHUNK = 1024
"""Candidate pairs per task of `_pair_rows`."""


@njit(parallel=True, cache=True)
def _pair_rows(pi, pj, x, v, omega, radius, mass, material, table, hist, slip, etan, dt, hp, per,
               h, lg, img, out):
    """Rows of all candidate pairs (any order of pairs, a periodic cell or not), chunks
    of PAIR_CHUNK over the threads."""
    m = pi.shape[0]
    nchunk = (m + PAIR_CHUNK - 1) // PAIR_CHUNK
    for t in prange(nchunk):
        b = spread(t, nchunk)
        _pair_rows_range(b * PAIR_CHUNK, min(m, (b + 1) * PAIR_CHUNK), pi, pj, x, v, omega,
                         radius, mass, material, table, hist, slip, etan, dt, hp, per, h, lg, img,
                         out)


@njit(cache=True)
def _pair_fused(pi, pj, x, v, omega, radius, mass, material, table, hist, slip, etan, dt, hp,
                per, h, lg, img, force, torque, fe, fd, td, hit):
    """Serial resolve-and-scatter over any pair list. Returns (elastic, spring) [J]. Pairs
    that are surely open are released without touching their parameter row."""
    e = 0.0
    es = 0.0
    mark = hit.shape[0] > 0
    for k in range(pi.shape[0]):
        i = pi[k]
        j = pj[k]
        if per:
            dx, dy, dz = _image(x, h, img, i, j, k)
            ux, uy, uz = _image_velocity(lg, dx, dy, dz)
        else:
            dx = x[j, 0] - x[i, 0]
            dy = x[j, 1] - x[i, 1]
            dz = x[j, 2] - x[i, 2]
            ux = uy = uz = 0.0
        rs = radius[i] + radius[j]
        d2 = dx * dx + dy * dy + dz * dz
        if d2 > rs * rs * _SURE_OPEN:
            _release(k, hist, slip, etan)
            continue
        d = math.sqrt(d2)
        delta = rs - d
        if delta <= 0.0:
            _release(k, hist, slip, etan)
            continue
        kin = _kin_ij(x, v, omega, radius, mass, i, j, dx, dy, dz, d, delta, ux, uy, uz)
        sx, sy, sz, sl, fo, vo, co = _history(k, hist, slip)
        r = _resolve(kin, _params(table, material[i], material[j]), sx, sy, sz, sl, fo, vo, co,
                     omega[i, 0] - omega[j, 0], omega[i, 1] - omega[j, 1],
                     omega[i, 2] - omega[j, 2], dt, hp)
        _put_history(k, r, hist, slip, etan)
        if r[18] == 0.0:
            continue
        if mark:
            hit[i] = 1
            hit[j] = 1
        _add_i(i, r, force, torque, fe, fd, td)
        _add_j(j, r, force, torque, fe, fd, td)
        e += r[18]
        es += r[22]
    return e, es


@njit(cache=True)
def _scatter(pi, pj, out, force, torque, fe, fd, td, hit):
    """Sum the touching rows onto particles in contact order (the additions of the fused
    loops, so the same bits). Returns (elastic energy, tangential spring energy) [J]."""
    e = 0.0
    es = 0.0
    mark = hit.shape[0] > 0
    for k in range(pi.shape[0]):
        if out[k, 18] == 0.0:
            continue  # not touching: the rest of the row is not written
        i = pi[k]
        j = pj[k]
        r = _row(out, k)
        if mark:
            hit[i] = 1
            hit[j] = 1
        _add_i(i, r, force, torque, fe, fd, td)
        _add_j(j, r, force, torque, fe, fd, td)
        e += r[18]
        es += r[22]
    return e, es


@njit(cache=True)
def pair_layout(pi, pj, n, hist, slip, etan):
    """Compact view of a pair list sorted by (i, j) for the kernels: start (n + 1,) int64
    (the pairs of i are start[i]:start[i + 1]), pj (m,) int32, live (m,) int8 (0 only
    where the contact history hist, slip, etan is all zero: hist[:, H_VN] is read only
    where hist[:, H_FN] is not zero), and the transpose: jstart
    (n + 1,) int64, jrow (m,) int64 (the pairs (i, j) with j = p, ascending i, are
    jrow[jstart[p]:jstart[p + 1]])."""
    m = pi.shape[0]
    start = np.zeros(n + 1, np.int64)
    jstart = np.zeros(n + 1, np.int64)
    for k in range(m):
        start[pi[k] + 1] += 1
        jstart[pj[k] + 1] += 1
    for i in range(n):
        start[i + 1] += start[i]
        jstart[i + 1] += jstart[i]
    pj32 = np.empty(m, np.int32)
    live = np.empty(m, np.int8)
    jrow = np.empty(m, np.int64)
    fill = jstart[:-1].copy()
    for k in range(m):
        pj32[k] = pj[k]
        live[k] = 1 if (etan[k] != 0.0 or slip[k] != 0 or hist[k, 0] != 0.0
                        or hist[k, 1] != 0.0 or hist[k, 2] != 0.0
                        or hist[k, H_FN] != 0.0) else 0
        jrow[fill[pj[k]]] = k
        fill[pj[k]] += 1
    return start, pj32, live, jstart, jrow


@njit(cache=True)
def refresh_live(hist, slip, etan, live):
    """live[k] = 0 where the history of contact k is all zero, else 1."""
    for k in range(live.shape[0]):
        live[k] = 1 if (etan[k] != 0.0 or slip[k] != 0 or hist[k, 0] != 0.0
                        or hist[k, 1] != 0.0 or hist[k, 2] != 0.0
                        or hist[k, H_FN] != 0.0) else 0


@njit(cache=True)
def _pair_csr(start, pj32, live, x, v, omega, radius, mass, material, table, hist, slip,
              etan, dt, hp, force, torque, fe, fd, td, hit):
    """`_pair_fused` without a cell, over the compact layout of `pair_layout`: particle i's
    position and radius are loaded once for all its partners, an open pair costs its
    4-byte partner index and, unless its history is known to be zero (live[k] = 0), a
    look at that history; a touching one is resolved on scalars and added to i and j at
    once. Same results, same order. (Keeping i's sums in registers over its partners was
    tried: slower, register pressure.)"""
    e = 0.0
    es = 0.0
    mark = hit.shape[0] > 0
    for i in range(start.shape[0] - 1):
        k0 = start[i]
        k1 = start[i + 1]
        if k0 == k1:
            continue
        xi0 = x[i, 0]
        xi1 = x[i, 1]
        xi2 = x[i, 2]
        ri = radius[i]
        mi = material[i]
        for k in range(k0, k1):
            j = np.int64(pj32[k])
            dx = x[j, 0] - xi0
            dy = x[j, 1] - xi1
            dz = x[j, 2] - xi2
            rs = ri + radius[j]
            d2 = dx * dx + dy * dy + dz * dz
            if d2 > rs * rs * _SURE_OPEN:
                if live[k]:
                    _release(k, hist, slip, etan)
                    live[k] = 0
                continue
            live[k] = 1
            d = math.sqrt(d2)
            delta = rs - d
            if delta <= 0.0:
                _release(k, hist, slip, etan)
                continue
            kin = _kin_ij(x, v, omega, radius, mass, i, j, dx, dy, dz, d, delta, 0.0, 0.0,
                          0.0)
            sx, sy, sz, sl, fo, vo, co = _history(k, hist, slip)
            r = _resolve(kin, _params(table, mi, material[j]), sx, sy, sz, sl, fo, vo, co,
                         omega[i, 0] - omega[j, 0], omega[i, 1] - omega[j, 1],
                         omega[i, 2] - omega[j, 2], dt, hp)
            _put_history(k, r, hist, slip, etan)
            if r[18] == 0.0:
                continue
            if mark:
                hit[i] = 1
                hit[j] = 1
            _add_i(i, r, force, torque, fe, fd, td)
            _add_j(j, r, force, torque, fe, fd, td)
            e += r[18]
            es += r[22]
    return e, es


ROWS_CHUNK = 256
"""Particles per chunk of `_pair_rows_csr`. The same as `GATHER_CHUNK` and
`dem.verlet.KD_CHUNK`, and all three spread the chunks alike: under a static schedule a
thread then works on the same particles in the three passes, and finds their rows in its
own cache (with 128 / 512 / 2048 the kick-drift pass did not speed up on two threads)."""
SPREAD = 7919
"""A prime: ``prange`` task b works on chunk ``spread(b, nchunk)``, so that the contiguous
blocks of tasks a static schedule gives each thread cover chunks from all over the
particle range (contacts cluster where the grains are loaded, e.g. at the bottom of a
settling bed: contiguous halves would leave one thread idle)."""


@njit(cache=True, inline="always")
def spread(b, nchunk):
    """Chunk of task b of nchunk: a permutation of range(nchunk) that strides by SPREAD."""
    b = np.int64(b)  # a prange index may be unsigned: int64 arithmetic, not float
    if nchunk % SPREAD == 0:
        return b
    return (b * SPREAD) % np.int64(nchunk)


# `_rows_range` repeats the pair body of `_pair_csr`, and `_wall_rows_range` the open test
# of `_wall_all`, on purpose: a shared body in an inlined helper would take arrays across
# branches (see the note above `apply_law`).
@njit(cache=True)
def _rows_range(lo, hi, start, pj32, live, x, v, omega, radius, mass, material, table, hist,
                slip, etan, dt, hp, out, touched):
    """The rows of the pairs of particles lo:hi (see `_pair_rows_csr`)."""
    for i in range(lo, hi):
        xi0 = x[i, 0]
        xi1 = x[i, 1]
        xi2 = x[i, 2]
        ri = radius[i]
        mi = material[i]
        for k in range(start[i], start[i + 1]):
            j = np.int64(pj32[k])
            dx = x[j, 0] - xi0
            dy = x[j, 1] - xi1
            dz = x[j, 2] - xi2
            rs = ri + radius[j]
            d2 = dx * dx + dy * dy + dz * dz
            if d2 > rs * rs * _SURE_OPEN:
                if live[k]:
                    _release(k, hist, slip, etan)
                    live[k] = 0
                continue
            live[k] = 1
            d = math.sqrt(d2)
            delta = rs - d
            if delta <= 0.0:
                out[k, 18] = 0.0
                _release(k, hist, slip, etan)
                continue
            kin = _kin_ij(x, v, omega, radius, mass, i, j, dx, dy, dz, d, delta, 0.0, 0.0,
                          0.0)
            sx, sy, sz, sl, fo, vo, co = _history(k, hist, slip)
            r = _resolve(kin, _params(table, mi, material[j]), sx, sy, sz, sl, fo, vo, co,
                         omega[i, 0] - omega[j, 0], omega[i, 1] - omega[j, 1],
                         omega[i, 2] - omega[j, 2], dt, hp)
            _put_history(k, r, hist, slip, etan)
            _put_row(out, k, r)
            if r[18] != 0.0:
                # j may lie in another thread's chunk: store only a change (two threads
                # may store the same 1; repeated stores would bounce the cache line)
                if touched[i] == 0:
                    touched[i] = 1
                if touched[j] == 0:
                    touched[j] = 1


@njit(parallel=True, cache=True)
def _pair_rows_csr(start, pj32, live, x, v, omega, radius, mass, material, table, hist, slip,
                   etan, dt, hp, out, touched):
    """`_pair_rows` without a cell over the compact layout, in chunks of ROWS_CHUNK
    particles i spread over the threads (each contact belongs to one i, so no two threads
    write the same row). Rows with live[k] = 0 afterwards are open and left
    unwritten (`_gather` skips them). touched (n,) int8, zero on entry: set to 1 for both
    particles of every touching contact (so that `_gather` skips the others without
    looking at their pairs)."""
    n = start.shape[0] - 1
    nchunk = (n + ROWS_CHUNK - 1) // ROWS_CHUNK
    for b in prange(nchunk):
        c = spread(b, nchunk)
        _rows_range(c * ROWS_CHUNK, min(n, (c + 1) * ROWS_CHUNK), start, pj32, live, x, v,
                    omega, radius, mass, material, table, hist, slip, etan, dt, hp, out, touched)


GATHER_CHUNK = 256
"""Particles per task of `_gather` (fixed: its energy sums do not depend on threads)."""


@njit(parallel=True, cache=True)
def _gather(start, jstart, jrow, live, out, force, torque, fe, fd, td, hit, part, touched):
    """Parallel, deterministic form of `_scatter` over the compact layout: each particle p
    sums its rows itself, first those where it is j (ascending i), then those where it is
    i (ascending j): the order in which `_scatter` adds them, so the same bits whatever the
    threads. part (nchunk, 2) receives the elastic and spring energies of the rows of the
    particles of each chunk of GATHER_CHUNK (summed by the caller in chunk order). Only
    particles flagged in touched (by `_pair_rows_csr`) are visited; the flags are cleared."""
    n = start.shape[0] - 1
    nchunk = part.shape[0]
    for t in prange(nchunk):
        b = spread(t, nchunk)
        e = 0.0
        es = 0.0
        for p in range(b * GATHER_CHUNK, min(n, (b + 1) * GATHER_CHUNK)):
            if touched[p] == 0:
                continue
            touched[p] = 0
            for q in range(jstart[p], jstart[p + 1]):
                k = jrow[q]
                if live[k] == 0 or out[k, 18] == 0.0:
                    continue
                hit[p] = 1
                for c in range(3):
                    force[p, c] += out[k, c]
                    torque[p, c] += out[k, 6 + c]
                    fe[p, c] += out[k, 19 + c]
                    fd[p, c] += out[k, 9 + c]
                    td[p, c] += out[k, 15 + c]
            for k in range(start[p], start[p + 1]):
                if live[k] == 0 or out[k, 18] == 0.0:
                    continue
                hit[p] = 1
                for c in range(3):
                    force[p, c] -= out[k, c]
                    torque[p, c] += out[k, 3 + c]
                    fe[p, c] -= out[k, 19 + c]
                    fd[p, c] -= out[k, 9 + c]
                    td[p, c] += out[k, 12 + c]
                e += out[k, 18]
                es += out[k, 22]
        part[b, 0] = e
        part[b, 1] = es


_TOUCHED = [np.zeros(0, np.int8)]


def _touched(n):
    """Zeroed (n,) int8 scratch flags for `_pair_rows_csr` / `_gather` (kept zero between
    calls: `_gather` clears what it reads)."""
    if _TOUCHED[0].shape[0] != n:
        _TOUCHED[0] = np.zeros(n, np.int8)
    return _TOUCHED[0]


def pair_forces(pi, pj, x, v, omega, radius, mass, material, table, hist, slip, etan, dt,
                out, force, torque, fe, fd, td, cell=NO_CELL, rows=False, hit=None,
                layout=None, horizon=0.0):
    """Add particle-particle contact forces to ``force``/``torque`` (n, 3), their
    conservative normal part to ``fe`` and their damping part to ``fd``/``td``.

    pi, pj (m,) int64 candidate pairs; hist (m, HIST) contact history (tangential springs
    [m], the dashpot's history: `dem.contact`); slip (m,) int8;
    etan (m,) spring energies [J]; out (>= m, NOUT) rows (written if ``rows`` or from
    ``PARALLEL_MIN`` candidate pairs on with more than one numba thread; else not used);
    cell: (flag, h (3, 3) [m], velocity gradient (3, 3) [1/s], image shifts (m, 3)) of a
    periodic cell.
    hit (n,) int8, optional: set to 1 for every particle that receives a contact.
    layout: `pair_layout` of (pi, pj) with live flags kept up to date by the kernels
    (without a cell only), or None.
    horizon: how far ahead [s] the normal dashpots predict the velocities given (dt/2 for
    the half-step velocities of velocity Verlet, 0: the velocities are those of the
    instant; `dem.contact.damping`).
    Returns (elastic energy [J], tangential spring energy [J])."""
    m = pi.shape[0]
    if m == 0:
        return 0.0, 0.0
    _check_history(hist, m, "pair_forces")
    hp = float(horizon)
    hit = _NOHIT if hit is None else hit
    per, h, lg, img = cell
    if layout is not None and per:
        raise ValueError("pair_forces: the compact layout is for runs without a cell")
    if rows or (m >= PARALLEL_MIN and get_num_threads() > 1):
        if layout is None:
            _pair_rows(pi, pj, x, v, omega, radius, mass, material, table, hist, slip, etan,
                       dt, hp, per, h, lg, img, out)
        else:
            start, pj32, live, jstart, jrow = layout
            touched = _touched(x.shape[0])
            _pair_rows_csr(start, pj32, live, x, v, omega, radius, mass, material, table, hist,
                           slip, etan, dt, hp, out, touched)
            if not rows and hit.shape[0] == x.shape[0]:
                part = np.empty(((x.shape[0] + GATHER_CHUNK - 1) // GATHER_CHUNK, 2))
                _gather(start, jstart, jrow, live, out, force, torque, fe, fd, td, hit, part,
                        touched)
                return float(part[:, 0].sum()), float(part[:, 1].sum())
            touched[:] = 0
            out[np.flatnonzero(live == 0), 18] = 0.0  # open rows, as `_scatter` reads them
        return _scatter(pi, pj, out, force, torque, fe, fd, td, hit)
    if layout is not None:
        return _pair_csr(*layout[:3], x, v, omega, radius, mass, material, table, hist, slip,
                         etan, dt, hp, force, torque, fe, fd, td, hit)
    return _pair_fused(pi, pj, x, v, omega, radius, mass, material, table, hist, slip, etan,
                       dt, hp, per, h, lg, img, force, torque, fe, fd, td, hit)


@njit(cache=True)
def _wall_all(wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u, wall_mat,
              table, hist, slip, etan, dt, hp, force, torque, fe, fd, td, wall_f, hit):
    """Serial wall contacts (few) straight into particles and walls. wall_f (nw, 9):
    resultant on each wall of the total, conservative normal and damping forces [N].
    Returns (elastic, spring) [J]."""
    e = 0.0
    es = 0.0
    mark = hit.shape[0] > 0
    for k in range(wi.shape[0]):
        i = wi[k]
        w = ww[k]
        delta = wall_delta(x, radius, i, wall_p, wall_n, w)
        if delta <= 0.0:  # open: release, no parameter row
            _release(k, hist, slip, etan)
            continue
        kin = _kin_wall(x, v, omega, radius, mass, i, wall_n, wall_u, w, delta)
        sx, sy, sz, sl, fo, vo, co = _history(k, hist, slip)
        r = _resolve(kin, _params(table, material[i], wall_mat[w]), sx, sy, sz, sl, fo, vo, co,
                     omega[i, 0], omega[i, 1], omega[i, 2], dt, hp)
        _put_history(k, r, hist, slip, etan)
        if r[18] == 0.0:
            continue
        if mark:
            hit[i] = 1
        _add_i(i, r, force, torque, fe, fd, td)
        _add_wall(w, r, wall_f)
        e += r[18]
        es += r[22]
    return e, es


@njit(cache=True)
def _wall_rows_range(lo, hi, wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n,
                     wall_u, wall_mat, table, hist, slip, etan, dt, hp, out):
    for k in range(lo, hi):
        i = wi[k]
        w = ww[k]
        delta = wall_delta(x, radius, i, wall_p, wall_n, w)
        if delta <= 0.0:
            _release(k, hist, slip, etan)
            out[k, 18] = 0.0
            continue
        kin = _kin_wall(x, v, omega, radius, mass, i, wall_n, wall_u, w, delta)
        sx, sy, sz, sl, fo, vo, co = _history(k, hist, slip)
        r = _resolve(kin, _params(table, material[i], wall_mat[w]), sx, sy, sz, sl, fo, vo, co,
                     omega[i, 0], omega[i, 1], omega[i, 2], dt, hp)
        _put_history(k, r, hist, slip, etan)
        _put_row(out, k, r)


WALL_CHUNK = 256
"""Wall candidates per task of `_wall_rows`."""


@njit(parallel=True, cache=True)
def _wall_rows(wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u, wall_mat,
               table, hist, slip, etan, dt, hp, out):
    """Rows of all wall candidates (out[k, 18] = 0 for open ones), chunks over threads."""
    m = wi.shape[0]
    nchunk = (m + WALL_CHUNK - 1) // WALL_CHUNK
    for t in prange(nchunk):
        b = spread(t, nchunk)
        _wall_rows_range(b * WALL_CHUNK, min(m, (b + 1) * WALL_CHUNK), wi, ww, x, v, omega,
                         radius, mass, material, wall_p, wall_n, wall_u, wall_mat, table, hist,
                         slip, etan, dt, hp, out)


@njit(cache=True)
def _wall_scatter(wi, ww, out, force, torque, fe, fd, td, wall_f, hit):
    """The touching rows of `_wall_rows` onto particles and walls in candidate order (the
    additions of `_wall_all`, so the same bits)."""
    e = 0.0
    es = 0.0
    mark = hit.shape[0] > 0
    for k in range(wi.shape[0]):
        if out[k, 18] == 0.0:
            continue
        i = wi[k]
        r = _row(out, k)
        if mark:
            hit[i] = 1
        _add_i(i, r, force, torque, fe, fd, td)
        _add_wall(ww[k], r, wall_f)
        e += r[18]
        es += r[22]
    return e, es


WALL_PARALLEL_MIN = 1024
"""Wall candidates from which, with more than one numba thread, `_wall_rows` runs."""


def wall_forces(wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u,
                wall_mat, table, hist, slip, etan, dt, out, force, torque, fe, fd, td,
                wall_f, hit=None, horizon=0.0):
    """Particle-wall forces, as `pair_forces` for (particle, wall) pairs wi, ww (m,);
    wall_f (nw, 9) receives the resultants on each wall of the total, conservative normal
    and damping forces [N]. Returns (elastic [J], spring energy [J])."""
    wall_f[:] = 0.0
    if wi.shape[0] == 0:
        return 0.0, 0.0
    _check_history(hist, wi.shape[0], "wall_forces")
    hp = float(horizon)
    hit = _NOHIT if hit is None else hit
    if wi.shape[0] >= WALL_PARALLEL_MIN and get_num_threads() > 1:
        _wall_rows(wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u,
                   wall_mat, table, hist, slip, etan, dt, hp, out)
        return _wall_scatter(wi, ww, out, force, torque, fe, fd, td, wall_f, hit)
    return _wall_all(wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u,
                     wall_mat, table, hist, slip, etan, dt, hp, force, torque, fe, fd, td, wall_f,
                     hit)
