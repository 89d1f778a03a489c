"""The one cached pair loop: particle-particle and particle-wall contact forces.

Each contact's kinematics is computed once (`dem.contact.kinematics`), the law is picked by
its integer id (``apply_law``: an integer switch, not a function argument, so numba's disk
cache works), and the per-contact forces are written to per-contact arrays in a ``prange``
loop; a serial scatter then sums them onto particles in a fixed order, so results do not
depend on the thread count or scheduling.
"""

from __future__ import annotations

import math

from numba import njit, prange

from dem.contact import P_LAW, P_MUR
from dem.contact.hertz_mindlin import hertz_mindlin_force
from dem.contact.kinematics import pair_kinematics, project_history, wall_kinematics
from dem.contact.linear import linear_force

NOUT = 12  # per-contact outputs: force on j (3), torques (3 + 3), energy, 2 powers

__all__ = ["NOUT", "apply_law", "pair_forces", "wall_forces"]


@njit(cache=True)
def apply_law(law, prm, delta, reff, meff, vn, vtx, vty, vtz, sx, sy, sz, slip, dt):
    """Law registry: id -> law function (ids in `dem.contact.LAWS`)."""
    if law == 0:
        return linear_force(prm, delta, reff, meff, vn, vtx, vty, vtz, sx, sy, sz, slip, dt)
    return hertz_mindlin_force(prm, delta, reff, meff, vn, vtx, vty, vtz, sx, sy, sz, slip, dt)


@njit(cache=True)
def _resolve(kin, prm, hist, slip, k, dt, wrx, wry, wrz):
    """Forces of one touching contact k. kin: kinematics tuple; wr: relative spin
    omega_i - omega_j [rad/s] for rolling resistance. Updates hist[k], slip[k]. Returns
    (force on j (3), torque on i (3), torque on j (3), elastic energy [J], power
    dissipated by damping and by friction (sliding + rolling) [W])."""
    nx, ny, nz, delta, reff, meff, vn, vtx, vty, vtz, ai, aj = kin
    sx, sy, sz = project_history(hist[k, 0], hist[k, 1], hist[k, 2], nx, ny, nz)
    fn, ftx, fty, ftz, sx, sy, sz, sl, e, pd, pf = apply_law(
        int(prm[P_LAW]), prm, delta, reff, meff, vn, vtx, vty, vtz, sx, sy, sz, slip[k], dt)
    hist[k, 0], hist[k, 1], hist[k, 2] = sx, sy, sz
    slip[k] = sl
    cx = ny * ftz - nz * fty  # n x ft
    cy = nz * ftx - nx * ftz
    cz = nx * fty - ny * ftx
    rix, riy, riz = -ai * cx, -ai * cy, -ai * cz
    rjx, rjy, rjz = -aj * cx, -aj * cy, -aj * cz
    mur = prm[P_MUR]
    w = math.sqrt(wrx * wrx + wry * wry + wrz * wrz)
    if mur > 0.0 and w > 0.0:
        mr = mur * abs(fn) * reff / w  # constant rolling torque against the relative spin
        rix -= mr * wrx
        riy -= mr * wry
        riz -= mr * wrz
        rjx += mr * wrx
        rjy += mr * wry
        rjz += mr * wrz
        pf += mr * w * w
    return (fn * nx + ftx, fn * ny + fty, fn * nz + ftz, rix, riy, riz, rjx, rjy, rjz, e, pd, pf)


@njit(parallel=True, cache=True)
def _pair_kernel(pi, pj, x, v, omega, radius, mass, material, table, hist, slip, dt, out):
    for k in prange(pi.shape[0]):
        i = pi[k]
        j = pj[k]
        kin = pair_kinematics(x, v, omega, radius, mass, i, j)
        if kin[3] <= 0.0:
            hist[k, 0] = hist[k, 1] = hist[k, 2] = 0.0
            slip[k] = 0
            for c in range(NOUT):
                out[k, c] = 0.0
            continue
        prm = table[material[i], material[j]]
        r = _resolve(kin, prm, hist, slip, k, dt, omega[i, 0] - omega[j, 0],
                     omega[i, 1] - omega[j, 1], omega[i, 2] - omega[j, 2])
        for c in range(NOUT):
            out[k, c] = r[c]


@njit(cache=True)
def _pair_scatter(pi, pj, out, force, torque):
    e = 0.0
    pd = 0.0
    pf = 0.0
    for k in range(pi.shape[0]):
        i = pi[k]
        j = pj[k]
        for c in range(3):
            force[i, c] -= out[k, c]
            force[j, c] += out[k, c]
            torque[i, c] += out[k, 3 + c]
            torque[j, c] += out[k, 6 + c]
        e += out[k, 9]
        pd += out[k, 10]
        pf += out[k, 11]
    return e, pd, pf


def pair_forces(pi, pj, x, v, omega, radius, mass, material, table, hist, slip, dt, out,
                force, torque):
    """Add particle-particle contact forces to ``force``/``torque`` (n, 3).

    pi, pj (m,) int64 candidate pairs; hist (m, 3) tangential springs [m], slip (m,) int8;
    out (m, NOUT) scratch. Returns (elastic energy [J], power dissipated by damping and by
    friction [W])."""
    if pi.shape[0] == 0:
        return 0.0, 0.0, 0.0
    _pair_kernel(pi, pj, x, v, omega, radius, mass, material, table, hist, slip, dt, out)
    return _pair_scatter(pi, pj, out, force, torque)


@njit(parallel=True, cache=True)
def _wall_kernel(wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u,
                 wall_mat, table, hist, slip, dt, out):
    for k in prange(wi.shape[0]):
        i = wi[k]
        w = ww[k]
        kin = wall_kinematics(x, v, omega, radius, mass, i, wall_p[w], wall_n[w], wall_u[w])
        if kin[3] <= 0.0:
            hist[k, 0] = hist[k, 1] = hist[k, 2] = 0.0
            slip[k] = 0
            for c in range(NOUT):
                out[k, c] = 0.0
            continue
        prm = table[material[i], wall_mat[w]]
        r = _resolve(kin, prm, hist, slip, k, dt, omega[i, 0], omega[i, 1], omega[i, 2])
        for c in range(NOUT):
            out[k, c] = r[c]


@njit(cache=True)
def _wall_scatter(wi, ww, wall_u, out, force, torque, wall_force):
    e = 0.0
    pd = 0.0
    pf = 0.0
    pw = 0.0
    for k in range(wi.shape[0]):
        i = wi[k]
        w = ww[k]
        for c in range(3):
            force[i, c] -= out[k, c]  # out holds the force on the wall ("particle j")
            torque[i, c] += out[k, 3 + c]
            wall_force[w, c] += out[k, c]
            pw -= out[k, c] * wall_u[w, c]
        e += out[k, 9]
        pd += out[k, 10]
        pf += out[k, 11]
    return e, pd, pf, pw


def wall_forces(wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u,
                wall_mat, table, hist, slip, dt, out, force, torque, wall_force):
    """Add particle-wall forces; wall_force (nw, 3) receives the resultant on each wall [N].

    wi, ww (m,) candidate (particle, wall) pairs. Returns (elastic energy [J], damping and
    friction power [W], power of the walls on the particles [W])."""
    wall_force[:] = 0.0
    if wi.shape[0] == 0:
        return 0.0, 0.0, 0.0, 0.0
    _wall_kernel(wi, ww, x, v, omega, radius, mass, material, wall_p, wall_n, wall_u,
                 wall_mat, table, hist, slip, dt, out)
    return _wall_scatter(wi, ww, wall_u, out, force, torque, wall_force)
