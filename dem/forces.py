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
- fused: one serial loop that resolves a contact into a scratch row and scatters it at
  once (no m x NOUT array streamed through memory twice).

Most candidate pairs of a Verlet list are open: a sqrt-free pre-test
(``d^2 > (r_i + r_j)^2 (1 + 1e-12)``, which implies delta <= 0 whatever the rounding)
releases them before their kinematics and parameter row are touched; walls use the exact
open test of `wall_kinematics` up front. Without a cell the integrator passes a compact
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
energy (`dem.integrate`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import get_num_threads, njit, prange

from dem.contact import P_LAW, P_MUR
from dem.contact.hertz_mindlin import hertz_mindlin_force
from dem.contact.kinematics import pair_kinematics, periodic_pair_kinematics, project_history, wall_kinematics
from dem.contact.linear import linear_force

NOUT = 23
PARALLEL_MIN = 4096
"""Candidate pairs from which, with more than one numba thread, the ``prange`` drivers run
(rows in chunks spread over the threads, then `_gather`). Settle scene (benchmarks/
dem_throughput.py), 2 threads on the 2-vCPU machine: see its results.json. The results are
the same bits whatever the driver and the thread count."""

__all__ = ["NOUT", "PARALLEL_MIN", "apply_law", "pair_forces", "pair_layout", "refresh_live",
           "wall_forces"]

_NOHIT = np.zeros(0, np.int8)

NO_CELL = (0, np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((0, 3)))
"""(periodic flag, h, velocity gradient, image shifts) of a simulation without a cell."""


@njit(cache=True, inline="always")
def apply_law(law, prm, delta, reff, meff, vn, vtx, vty, vtz, sx, sy, sz, slip, dt):
    """Law registry: id -> law function (ids in `dem.contact.LAWS`)."""
    if law == 0:
        return linear_force(prm, delta, reff, meff, vn, vtx, vty, vtz, sx, sy, sz, slip, dt)
    return hertz_mindlin_force(prm, delta, reff, meff, vn, vtx, vty, vtz, sx, sy, sz, slip, dt)


@njit(cache=True, inline="always")
def _cross_arm(out, col, nx, ny, nz, fx, fy, fz, ai, aj):
    """Torques -a n x f on i (cols col..col+2) and j (col+3..col+5)."""
    cx = ny * fz - nz * fy
    cy = nz * fx - nx * fz
    cz = nx * fy - ny * fx
    out[col], out[col + 1], out[col + 2] = -ai * cx, -ai * cy, -ai * cz
    out[col + 3], out[col + 4], out[col + 5] = -aj * cx, -aj * cy, -aj * cz


@njit(cache=True, inline="always")
def _contact(k, kin, prm, hist, slip, etan, dt, wrx, wry, wrz, out):
    """Resolve contact k with kinematics ``kin``; wr = omega_i - omega_j [rad/s] (rolling).
    Writes row out (NOUT,); updates hist[k], slip[k], etan[k]."""
    nx, ny, nz, delta, reff, meff, vn, vtx, vty, vtz, ai, aj = kin
    if delta <= 0.0:  # open: only column 18 is written; a loaded spring is released
        out[18] = 0.0
        if etan[k] != 0.0 or slip[k] != 0 or hist[k, 0] != 0.0 or hist[k, 1] != 0.0 \
                or hist[k, 2] != 0.0:
            hist[k, 0] = hist[k, 1] = hist[k, 2] = 0.0
            slip[k] = 0
            etan[k] = 0.0
        return
    sx, sy, sz = project_history(hist[k, 0], hist[k, 1], hist[k, 2], nx, ny, nz)
    fn, fnd, ftx, fty, ftz, fdx, fdy, fdz, sx, sy, sz, sl, e_n, e_pre, e_t, p_fric = \
        apply_law(int(prm[P_LAW]), prm, delta, reff, meff, vn, vtx, vty, vtz, sx, sy, sz,
                  slip[k], dt)
    hist[k, 0], hist[k, 1], hist[k, 2] = sx, sy, sz
    slip[k] = sl
    out[0], out[1], out[2] = fn * nx + ftx, fn * ny + fty, fn * nz + ftz
    out[9], out[10], out[11] = fnd * nx + fdx, fnd * ny + fdy, fnd * nz + fdz
    fe = fn - fnd
    out[19], out[20], out[21] = fe * nx, fe * ny, fe * nz
    _cross_arm(out, 3, nx, ny, nz, ftx, fty, ftz, ai, aj)
    _cross_arm(out, 12, nx, ny, nz, fdx, fdy, fdz, ai, aj)
    mur = prm[P_MUR]
    if mur > 0.0:
        w = math.sqrt(wrx * wrx + wry * wry + wrz * wrz)
        if w > 0.0:
            mr = mur * abs(fn) * reff / w  # constant rolling torque against the relative spin
            out[3] -= mr * wrx
            out[4] -= mr * wry
            out[5] -= mr * wrz
            out[6] += mr * wrx
            out[7] += mr * wry
            out[8] += mr * wrz
    out[18] = e_n + e_t
    out[22] = e_t
    etan[k] = e_t


_SURE_OPEN = 1.0 + 1e-12
"""d^2 > (r_i + r_j)^2 x this: the pair is open whatever the rounding of d = sqrt(d^2)."""


@njit(cache=True, inline="always")
def _release(k, hist, slip, etan):
    """An open contact k: a loaded spring is released (as `_contact` does)."""
    if etan[k] != 0.0 or slip[k] != 0 or hist[k, 0] != 0.0 or hist[k, 1] != 0.0 \
            or hist[k, 2] != 0.0:
        hist[k, 0] = hist[k, 1] = hist[k, 2] = 0.0
        slip[k] = 0
        etan[k] = 0.0


@njit(cache=True, inline="always")
def _surely_open(x, radius, i, j):
    """Cheap pre-test (no sqrt, no parameter row): True only for pairs `_contact` would
    find open (delta <= 0), so skipping them changes no result bit."""
    dx = x[j, 0] - x[i, 0]
    dy = x[j, 1] - x[i, 1]
    dz = x[j, 2] - x[i, 2]
    rs = radius[i] + radius[j]
    return dx * dx + dy * dy + dz * dz > rs * rs * _SURE_OPEN


@njit(cache=True, inline="always")
def _pair_one(k, pi, pj, x, v, omega, radius, mass, material, table, hist, slip, etan, dt,
              per, h, lg, img, out):
    i = pi[k]
    j = pj[k]
    if not per and _surely_open(x, radius, i, j):
        out[18] = 0.0
        _release(k, hist, slip, etan)
        return
    if per:
        kin = periodic_pair_kinematics(x, v, omega, radius, mass, i, j, h, lg, img[k, 0],
                                       img[k, 1], img[k, 2])
    else:
        kin = pair_kinematics(x, v, omega, radius, mass, i, j)
    _contact(k, kin, table[material[i], material[j]], hist, slip, etan, dt,
             omega[i, 0] - omega[j, 0], omega[i, 1] - omega[j, 1], omega[i, 2] - omega[j, 2],
             out)


@njit(cache=True, inline="always")
def _scatter_row(i, j, row, force, torque, fe, fd, td, hit):
    """Add one touching row to particles i and j (j < 0: a wall, i only); flag them in hit
    (n,) int8 (if not empty): the integrator then knows whose force arrays are non-zero."""
    if hit.shape[0] > 0:
        hit[i] = 1
        if j >= 0:
            hit[j] = 1
    for c in range(3):
        force[i, c] -= row[c]
        torque[i, c] += row[3 + c]
        fe[i, c] -= row[19 + c]
        fd[i, c] -= row[9 + c]
        td[i, c] += row[12 + c]
        if j >= 0:
            force[j, c] += row[c]
            torque[j, c] += row[6 + c]
            fe[j, c] += row[19 + c]
            fd[j, c] += row[9 + c]
            td[j, c] += row[15 + c]


@njit(parallel=True, cache=True)
def _pair_rows(pi, pj, x, v, omega, radius, mass, material, table, hist, slip, etan, dt, per,
               h, lg, img, out):
    for k in prange(pi.shape[0]):
        _pair_one(k, pi, pj, x, v, omega, radius, mass, material, table, hist, slip, etan,
                  dt, per, h, lg, img, out[k])


@njit(cache=True)
def _pair_fused(pi, pj, x, v, omega, radius, mass, material, table, hist, slip, etan, dt,
                per, h, lg, img, row, force, torque, fe, fd, td, hit):
    """Serial resolve-and-scatter; row (NOUT,) scratch. Returns (elastic, spring) [J].
    Without a cell, pairs that are surely open are released without touching their
    parameter row (one loop per case: a shared loop body compiles to slow code)."""
    e = 0.0
    es = 0.0
    if per:
        for k in range(pi.shape[0]):
            i = pi[k]
            j = pj[k]
            kin = periodic_pair_kinematics(x, v, omega, radius, mass, i, j, h, lg, img[k, 0],
                                           img[k, 1], img[k, 2])
            _contact(k, kin, table[material[i], material[j]], hist, slip, etan, dt,
                     omega[i, 0] - omega[j, 0], omega[i, 1] - omega[j, 1],
                     omega[i, 2] - omega[j, 2], row)
            if row[18] == 0.0:
                continue
            _scatter_row(i, j, row, force, torque, fe, fd, td, hit)
            e += row[18]
            es += row[22]
        return e, es
    for k in range(pi.shape[0]):
        i = pi[k]
        j = pj[k]
        if _surely_open(x, radius, i, j):
            _release(k, hist, slip, etan)
            continue
        kin = pair_kinematics(x, v, omega, radius, mass, i, j)
        _contact(k, kin, table[material[i], material[j]], hist, slip, etan, dt,
                 omega[i, 0] - omega[j, 0], omega[i, 1] - omega[j, 1],
                 omega[i, 2] - omega[j, 2], row)
        if row[18] == 0.0:
            continue
        _scatter_row(i, j, row, force, torque, fe, fd, td, hit)
        e += row[18]
        es += row[22]
    return e, es


@njit(cache=True)
def _scatter(pi, pj, out, force, torque, fe, fd, td, hit):
    """Sum rows onto particles in contact order (pj < 0: wall contacts, i only). Returns
    (elastic energy, tangential spring energy) [J]."""
    e = 0.0
    es = 0.0
    for k in range(pi.shape[0]):
        if out[k, 18] == 0.0:
            continue  # not touching: the rest of the row is not written
        _scatter_row(pi[k], pj[k], out[k], force, torque, fe, fd, td, hit)
        e += out[k, 18]
        es += out[k, 22]
    return e, es


@njit(cache=True)
def pair_layout(pi, pj, n, hist, slip, etan):
    """Compact view of a pair list sorted by (i, j) for the kernels: start (n + 1,) int64
    (the pairs of i are start[i]:start[i + 1]), pj (m,) int32, live (m,) int8 (0 only
    where the contact history hist, slip, etan is all zero), and the transpose: jstart
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
                        or hist[k, 1] != 0.0 or hist[k, 2] != 0.0) else 0
        jrow[fill[pj[k]]] = k
        fill[pj[k]] += 1
    return start, pj32, live, jstart, jrow


@njit(cache=True)
def refresh_live(hist, slip, etan, live):
    """live[k] = 0 where the history of contact k is all zero, else 1."""
    for k in range(live.shape[0]):
        live[k] = 1 if (etan[k] != 0.0 or slip[k] != 0 or hist[k, 0] != 0.0
                        or hist[k, 1] != 0.0 or hist[k, 2] != 0.0) else 0


@njit(cache=True)
def _pair_csr(start, pj32, live, x, v, omega, radius, mass, material, table, hist, slip,
              etan, dt, row, force, torque, fe, fd, td, hit):
    """`_pair_fused` without a cell, over the compact layout of `pair_layout`: particle i's
    position and radius are loaded once for all its partners, an open pair costs its
    4-byte partner index and, unless its history is known to be zero (live[k] = 0), a
    look at that history. Same results, same order. (Keeping i's sums in registers over
    its partners was tried: slower, register pressure.)"""
    e = 0.0
    es = 0.0
    for i in range(start.shape[0] - 1):
        k0 = start[i]
        k1 = start[i + 1]
        if k0 == k1:
            continue
        xi0 = x[i, 0]
        xi1 = x[i, 1]
        xi2 = x[i, 2]
        ri = radius[i]
        for k in range(k0, k1):
            j = np.int64(pj32[k])
            dx = x[j, 0] - xi0
            dy = x[j, 1] - xi1
            dz = x[j, 2] - xi2
            rs = ri + radius[j]
            if dx * dx + dy * dy + dz * dz > rs * rs * _SURE_OPEN:
                if live[k]:
                    _release(k, hist, slip, etan)
                    live[k] = 0
                continue
            live[k] = 1
            kin = pair_kinematics(x, v, omega, radius, mass, i, j)
            _contact(k, kin, table[material[i], material[j]], hist, slip, etan, dt,
                     omega[i, 0] - omega[j, 0], omega[i, 1] - omega[j, 1],
                     omega[i, 2] - omega[j, 2], row)
            if row[18] == 0.0:
                continue
            _scatter_row(i, j, row, force, torque, fe, fd, td, hit)
            e += row[18]
            es += row[22]
    return e, es


ROWS_CHUNK = 256
"""Particles per chunk of `_pair_rows_csr`. The same as `GATHER_CHUNK` and
`dem.integrate.KD_CHUNK`, and all three spread the chunks alike: under a static schedule a
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


# `_rows_range` repeats the pair body of `_pair_csr`, and `_wall_rows_range` /
# `_wall_scatter` the open test and wall scatter of `_wall_all`, on purpose: the shared
# body as an inline="always" helper returning whether the pair touches measured 6x slower
# in `_pair_csr` (settle scene, 10k grains: 2000 vs 340 us per step) and 25 % slower in
# `_wall_all`, with the same bits.
@njit(cache=True)
def _rows_range(lo, hi, start, pj32, live, x, v, omega, radius, mass, material, table, hist,
                slip, etan, dt, out, touched):
    """The rows of the pairs of particles lo:hi (see `_pair_rows_csr`)."""
    for i in range(lo, hi):
        xi0 = x[i, 0]
        xi1 = x[i, 1]
        xi2 = x[i, 2]
        ri = radius[i]
        for k in range(start[i], start[i + 1]):
            j = np.int64(pj32[k])
            dx = x[j, 0] - xi0
            dy = x[j, 1] - xi1
            dz = x[j, 2] - xi2
            rs = ri + radius[j]
            if dx * dx + dy * dy + dz * dz > rs * rs * _SURE_OPEN:
                if live[k]:
                    _release(k, hist, slip, etan)
                    live[k] = 0
                continue
            live[k] = 1
            kin = pair_kinematics(x, v, omega, radius, mass, i, j)
            _contact(k, kin, table[material[i], material[j]], hist, slip, etan, dt,
                     omega[i, 0] - omega[j, 0], omega[i, 1] - omega[j, 1],
                     omega[i, 2] - omega[j, 2], out[k])
            if out[k, 18] != 0.0:
                # j may lie in another thread's chunk: store only a change (two threads
                # may store the same 1; repeated stores would bounce the cache line)
                if touched[i] == 0:
                    touched[i] = 1
                if touched[j] == 0:
                    touched[j] = 1


@njit(parallel=True, cache=True)
def _pair_rows_csr(start, pj32, live, x, v, omega, radius, mass, material, table, hist, slip,
                   etan, dt, out, touched):
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
                    omega, radius, mass, material, table, hist, slip, etan, dt, out, touched)


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
                layout=None):
    """Add particle-particle contact forces to ``force``/``torque`` (n, 3), their
    conservative normal part to ``fe`` and their damping part to ``fd``/``td``.

    pi, pj (m,) int64 candidate pairs; hist (m, 3) tangential springs [m]; slip (m,) int8;
    etan (m,) spring energies [J]; out (>= m, NOUT) rows (written if ``rows`` or from
    ``PARALLEL_MIN`` candidate pairs on with more than one numba thread; else only out[0]
    is used as scratch); cell: (flag, h
    (3, 3) [m], velocity gradient (3, 3) [1/s], image shifts (m, 3)) of a periodic cell.
    hit (n,) int8, optional: set to 1 for every particle that receives a contact.
    layout: `pair_layout` of (pi, pj) with live flags kept up to date by the kernels
    (without a cell only), or None.
    Returns (elastic energy [J], tangential spring energy [J])."""
    m = pi.shape[0]
    if m == 0:
        return 0.0, 0.0
    hit = _NOHIT if hit is None else hit
    per, h, lg, img = cell
    if layout is not None and per:
        raise ValueError("pair_forces: the compact layout is for runs without a cell")
    if rows or (m >= PARALLEL_MIN and get_num_threads() > 1):
        if layout is None:
            _pair_rows(pi, pj, x, v, omega, radius, mass, material, table, hist, slip, etan,
                       dt, per, h, lg, img, out)
        else:
            start, pj32, live, jstart, jrow = layout
            touched = _touched(x.shape[0])
            _pair_rows_csr(start, pj32, live, x, v, omega, radius, mass, material, table, hist,
                           slip, etan, dt, out, touched)
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
                         etan, dt, out[0], force, torque, fe, fd, td, hit)
    return _pair_fused(pi, pj, x, v, omega, radius, mass, material, table, hist, slip, etan,
                       dt, per, h, lg, img, out[0], force, torque, fe, fd, td, hit)


@njit(cache=True, inline="always")
def _wall_one(k, wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u,
              wall_mat, table, hist, slip, etan, dt, out):
    i = wi[k]
    w = ww[k]
    kin = wall_kinematics(x, v, omega, radius, mass, i, wall_p, wall_n, wall_u, w)
    _contact(k, kin, table[material[i], wall_mat[w]], hist, slip, etan, dt,
             omega[i, 0], omega[i, 1], omega[i, 2], out)


@njit(cache=True)
def _wall_all(wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u, wall_mat,
              table, hist, slip, etan, dt, out, force, torque, fe, fd, td, wall_f, hit):
    """Serial wall contacts (few) straight into particles and walls. wall_f (nw, 9):
    resultant on each wall of the total, conservative normal and damping forces [N].
    Returns (elastic, spring) [J]."""
    e = 0.0
    es = 0.0
    row = out[0]
    for k in range(wi.shape[0]):
        i = wi[k]
        w = ww[k]
        # open (the test of `wall_kinematics`, same arithmetic): release, no parameter row
        if radius[i] - ((x[i, 0] - wall_p[w, 0]) * wall_n[w, 0]
                        + (x[i, 1] - wall_p[w, 1]) * wall_n[w, 1]
                        + (x[i, 2] - wall_p[w, 2]) * wall_n[w, 2]) <= 0.0:
            _release(k, hist, slip, etan)
            continue
        _wall_one(k, wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u,
                  wall_mat, table, hist, slip, etan, dt, row)
        if row[18] == 0.0:
            continue
        _scatter_row(i, -1, row, force, torque, fe, fd, td, hit)
        for c in range(3):  # the row's "particle j" is the wall
            wall_f[w, c] += row[c]
            wall_f[w, 3 + c] += row[19 + c]
            wall_f[w, 6 + c] += row[9 + c]
        e += row[18]
        es += row[22]
    return e, es


@njit(cache=True)
def _wall_rows_range(lo, hi, wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n,
                     wall_u, wall_mat, table, hist, slip, etan, dt, out):
    for k in range(lo, hi):
        i = wi[k]
        w = ww[k]
        if radius[i] - ((x[i, 0] - wall_p[w, 0]) * wall_n[w, 0]
                        + (x[i, 1] - wall_p[w, 1]) * wall_n[w, 1]
                        + (x[i, 2] - wall_p[w, 2]) * wall_n[w, 2]) <= 0.0:
            _release(k, hist, slip, etan)
            out[k, 18] = 0.0
            continue
        _wall_one(k, wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u,
                  wall_mat, table, hist, slip, etan, dt, out[k])


WALL_CHUNK = 256
"""Wall candidates per task of `_wall_rows`."""


@njit(parallel=True, cache=True)
def _wall_rows(wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u, wall_mat,
               table, hist, slip, etan, dt, out):
    """Rows of all wall candidates (out[k, 18] = 0 for open ones), chunks over threads."""
    m = wi.shape[0]
    nchunk = (m + WALL_CHUNK - 1) // WALL_CHUNK
    for t in prange(nchunk):
        b = spread(t, nchunk)
        _wall_rows_range(b * WALL_CHUNK, min(m, (b + 1) * WALL_CHUNK), wi, ww, x, v, omega,
                         radius, mass, material, wall_p, wall_n, wall_u, wall_mat, table, hist,
                         slip, etan, dt, out)


@njit(cache=True)
def _wall_scatter(wi, ww, out, force, torque, fe, fd, td, wall_f, hit):
    """The touching rows of `_wall_rows` onto particles and walls in candidate order (the
    additions of `_wall_all`, so the same bits)."""
    e = 0.0
    es = 0.0
    for k in range(wi.shape[0]):
        row = out[k]
        if row[18] == 0.0:
            continue
        _scatter_row(wi[k], -1, row, force, torque, fe, fd, td, hit)
        w = ww[k]
        for c in range(3):
            wall_f[w, c] += row[c]
            wall_f[w, 3 + c] += row[19 + c]
            wall_f[w, 6 + c] += row[9 + c]
        e += row[18]
        es += row[22]
    return e, es


WALL_PARALLEL_MIN = 1024
"""Wall candidates from which, with more than one numba thread, `_wall_rows` runs."""


def wall_forces(wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u,
                wall_mat, table, hist, slip, etan, dt, out, force, torque, fe, fd, td,
                wall_f, hit=None):
    """Particle-wall forces, as `pair_forces` for (particle, wall) pairs wi, ww (m,);
    wall_f (nw, 9) receives the resultants on each wall of the total, conservative normal
    and damping forces [N]. Returns (elastic [J], spring energy [J])."""
    wall_f[:] = 0.0
    if wi.shape[0] == 0:
        return 0.0, 0.0
    hit = _NOHIT if hit is None else hit
    if wi.shape[0] >= WALL_PARALLEL_MIN and get_num_threads() > 1:
        _wall_rows(wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u,
                   wall_mat, table, hist, slip, etan, dt, out)
        return _wall_scatter(wi, ww, out, force, torque, fe, fd, td, wall_f, hit)
    return _wall_all(wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u,
                     wall_mat, table, hist, slip, etan, dt, out, force, torque, fe, fd, td,
                     wall_f, hit)
