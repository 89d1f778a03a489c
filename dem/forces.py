"""The one cached pair loop: particle-particle and particle-wall contact forces.

Each contact's kinematics is computed once (`dem.contact.kinematics`), the law is picked by
its integer id (``apply_law``: an integer switch, not a function argument, so numba's disk
cache works), and the per-contact results are written to rows of ``out`` in a ``prange``
loop (a plain loop below ``PARALLEL_MIN`` contacts, where thread start-up costs more than
it saves); a serial scatter then sums them onto particles in a fixed order, so results do
not depend on the thread count or scheduling.

Row layout of ``out`` (NOUT = 20): force on j [N] (0:3), torque on i (3:6) and on j
(6:9) [N m]; their dissipative parts (dashpots, clipping, rolling resistance): force on j
(9:12), torque on i (12:15), on j (15:18); elastic energy [J] (18, > 0 iff touching;
rows of open contacts are only valid in 18-20); energy lost by the
tangential spring other than through work this step [J] (19: change while sliding,
projection onto the new tangent plane, stiffness change, release when the contact opens);
friction dissipation estimate (sliding power x dt + column 19) [J] (20).
"""

from __future__ import annotations

import math

from numba import njit, prange

from dem.contact import P_LAW, P_MUR
from dem.contact.hertz_mindlin import hertz_mindlin_force
from dem.contact.kinematics import pair_kinematics, project_history, wall_kinematics
from dem.contact.linear import linear_force

NOUT = 21
PARALLEL_MIN = 4096

__all__ = ["NOUT", "PARALLEL_MIN", "apply_law", "pair_forces", "wall_forces"]


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
    if delta <= 0.0:  # open: only the columns the scatter tests (18, 20) are written
        out[18] = 0.0
        out[19] = out[20] = etan[k]  # a loaded spring is released when the contact opens
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
    _cross_arm(out, 3, nx, ny, nz, ftx, fty, ftz, ai, aj)
    _cross_arm(out, 12, nx, ny, nz, fdx, fdy, fdz, ai, aj)
    mur = prm[P_MUR]
    fric = p_fric * dt
    w = math.sqrt(wrx * wrx + wry * wry + wrz * wrz)
    if mur > 0.0 and w > 0.0:
        mr = mur * abs(fn) * reff / w  # constant rolling torque against the relative spin
        for c, wc in ((0, wrx), (1, wry), (2, wrz)):
            out[3 + c] -= mr * wc
            out[6 + c] += mr * wc
            out[12 + c] -= mr * wc
            out[15 + c] += mr * wc
        fric += mr * w * dt
    out[18] = e_n + e_t
    out[19] = etan[k] - (e_t if sl else e_pre)  # sliding: the spring force is dissipative
    out[20] = fric + out[19]
    etan[k] = e_t


@njit(cache=True, inline="always")
def _pair_one(k, pi, pj, x, v, omega, radius, mass, material, table, hist, slip, etan, dt,
              out):
    i = pi[k]
    j = pj[k]
    kin = pair_kinematics(x, v, omega, radius, mass, i, j)
    _contact(k, kin, table[material[i], material[j]], hist, slip, etan, dt,
             omega[i, 0] - omega[j, 0], omega[i, 1] - omega[j, 1], omega[i, 2] - omega[j, 2],
             out[k])


@njit(parallel=True, cache=True)
def _pair_par(pi, pj, x, v, omega, radius, mass, material, table, hist, slip, etan, dt, out):
    for k in prange(pi.shape[0]):
        _pair_one(k, pi, pj, x, v, omega, radius, mass, material, table, hist, slip, etan,
                  dt, out)


@njit(cache=True)
def _pair_ser(pi, pj, x, v, omega, radius, mass, material, table, hist, slip, etan, dt, out):
    for k in range(pi.shape[0]):
        _pair_one(k, pi, pj, x, v, omega, radius, mass, material, table, hist, slip, etan,
                  dt, out)


@njit(cache=True)
def _scatter(pi, pj, out, force, torque, fd, td):
    """Sum rows onto particles (pj < 0: wall contacts, i only). Returns (elastic, spring
    loss, friction estimate) [J]."""
    e = 0.0
    loss = 0.0
    fric = 0.0
    for k in range(pi.shape[0]):
        loss += out[k, 19]
        fric += out[k, 20]
        if out[k, 18] == 0.0:
            continue  # not touching: the rest of the row is not written
        i = pi[k]
        j = pj[k]
        for c in range(3):
            force[i, c] -= out[k, c]
            torque[i, c] += out[k, 3 + c]
            fd[i, c] -= out[k, 9 + c]
            td[i, c] += out[k, 12 + c]
            if j >= 0:
                force[j, c] += out[k, c]
                torque[j, c] += out[k, 6 + c]
                fd[j, c] += out[k, 9 + c]
                td[j, c] += out[k, 15 + c]
        e += out[k, 18]
    return e, loss, fric


def pair_forces(pi, pj, x, v, omega, radius, mass, material, table, hist, slip, etan, dt,
                out, force, torque, fd, td):
    """Add particle-particle contact forces to ``force``/``torque`` (n, 3) and their
    dissipative parts to ``fd``/``td``. pi, pj (m,) int64 candidate pairs; hist (m, 3)
    tangential springs [m]; slip (m,) int8; etan (m,) spring energies [J]; out (>= m,
    NOUT) scratch. Returns (elastic energy [J], tangential spring loss this step [J],
    friction dissipation estimate this step [J])."""
    m = pi.shape[0]
    if m == 0:
        return 0.0, 0.0, 0.0
    kern = _pair_par if m >= PARALLEL_MIN else _pair_ser
    kern(pi, pj, x, v, omega, radius, mass, material, table, hist, slip, etan, dt, out)
    return _scatter(pi, pj, out, force, torque, fd, td)


@njit(cache=True, inline="always")
def _wall_one(k, wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u,
              wall_mat, table, hist, slip, etan, dt, out):
    i = wi[k]
    w = ww[k]
    kin = wall_kinematics(x, v, omega, radius, mass, i, wall_p, wall_n, wall_u, w)
    _contact(k, kin, table[material[i], wall_mat[w]], hist, slip, etan, dt,
             omega[i, 0], omega[i, 1], omega[i, 2], out[k])


@njit(parallel=True, cache=True)
def _wall_par(wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u, wall_mat,
              table, hist, slip, etan, dt, out):
    for k in prange(wi.shape[0]):
        _wall_one(k, wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u,
                  wall_mat, table, hist, slip, etan, dt, out)


@njit(cache=True)
def _wall_ser(wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u, wall_mat,
              table, hist, slip, etan, dt, out):
    for k in range(wi.shape[0]):
        _wall_one(k, wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u,
                  wall_mat, table, hist, slip, etan, dt, out)


@njit(cache=True)
def _wall_resultant(wi, ww, wall_u, out, wall_force):
    pw = 0.0
    for k in range(wi.shape[0]):
        if out[k, 18] == 0.0:
            continue
        w = ww[k]
        for c in range(3):
            wall_force[w, c] += out[k, c]  # row = force on the wall ("particle j")
            pw -= out[k, c] * wall_u[w, c]
    return pw


def wall_forces(wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u,
                wall_mat, table, hist, slip, etan, dt, out, force, torque, fd, td,
                wall_force):
    """Particle-wall forces, as `pair_forces` for (particle, wall) pairs wi, ww (m,);
    wall_force (nw, 3) receives the resultant on each wall [N]. Returns (elastic [J],
    spring loss [J], friction estimate [J], power of the walls on the particles [W])."""
    wall_force[:] = 0.0
    m = wi.shape[0]
    if m == 0:
        return 0.0, 0.0, 0.0, 0.0
    kern = _wall_par if m >= PARALLEL_MIN else _wall_ser
    kern(wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u, wall_mat,
         table, hist, slip, etan, dt, out)
    e, loss, fric = _scatter(wi, -1 - ww, out, force, torque, fd, td)
    return e, loss, fric, _wall_resultant(wi, ww, wall_u, out, wall_force)
