"""Pair kinematics, computed once per contact; laws only read them (STYLE.md rule 6).

Conventions: ``n`` is the unit normal from particle i to j (for a wall contact: from the
particle to the wall); overlap ``delta = r_i + r_j - |x_j - x_i|`` > 0 in contact;
``vn = (v_c,i - v_c,j) . n`` (> 0 approaching, = d delta/dt) and ``vt`` the tangential
part of the relative contact-point velocity of i with respect to j. Contact-point arms are
``r - delta/2`` (LIGGGHTS). The tangential force returned by a law acts on j along
``+ft`` and on i along ``-ft``; the normal force ``fn`` pushes j along ``+n``.
"""

from __future__ import annotations

import math

from numba import njit

__all__ = ["contact_kinematics", "coulomb_tangential", "pair_kinematics",
           "periodic_pair_kinematics", "project_history", "wall_contact_kinematics", "wall_delta",
           "wall_kinematics"]


@njit(cache=True, inline="always")
def _relative(nx, ny, nz, vix, viy, viz, vjx, vjy, vjz, wx, wy, wz):
    """Relative contact velocity v_i - v_j + w x n with w = a_i w_i + a_j w_j."""
    rx = vix - vjx + (wy * nz - wz * ny)
    ry = viy - vjy + (wz * nx - wx * nz)
    rz = viz - vjz + (wx * ny - wy * nx)
    vn = rx * nx + ry * ny + rz * nz
    return vn, rx - vn * nx, ry - vn * ny, rz - vn * nz


@njit(cache=True, inline="always")
def contact_kinematics(dx, dy, dz, d, delta, ri, rj, mi, mj, vix, viy, viz, vjx, vjy, vjz,
                       oix, oiy, oiz, ojx, ojy, ojz):
    """Kinematics of a touching pair (delta > 0) from scalars only: branch d = (dx, dy, dz)
    from i to j [m], |d|, overlap, radii, masses, velocities v_i, v_j (with any image
    velocity) and spins omega_i, omega_j. Same return layout as `pair_kinematics` (zero
    but for delta when d = 0: coincident centres have no normal). Scalars, not arrays: an
    array passed into an inlined helper that branches costs numba an atomic reference
    count per call, which dominated the dense pair loops."""
    if d == 0.0:
        return 0.0, 0.0, 0.0, delta, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    nx, ny, nz = dx / d, dy / d, dz / d
    ai = ri - 0.5 * delta
    aj = rj - 0.5 * delta
    wx = ai * oix + aj * ojx
    wy = ai * oiy + aj * ojy
    wz = ai * oiz + aj * ojz
    vn, vtx, vty, vtz = _relative(nx, ny, nz, vix, viy, viz, vjx, vjy, vjz, wx, wy, wz)
    reff = ri * rj / (ri + rj)
    meff = mi * mj / (mi + mj)
    return nx, ny, nz, delta, reff, meff, vn, vtx, vty, vtz, ai, aj


@njit(cache=True, inline="always")
def _branch_kinematics(v, omega, radius, mass, i, j, dx, dy, dz, ux, uy, uz):
    """Kinematics of pair (i, j) with branch vector d = (dx, dy, dz) from i to j [m] and an
    extra velocity u [m/s] of j's image relative to j (periodic cells; else 0)."""
    d = math.sqrt(dx * dx + dy * dy + dz * dz)
    ri = radius[i]
    rj = radius[j]
    delta = ri + rj - d
    if delta <= 0.0:
        return 0.0, 0.0, 0.0, delta, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    return contact_kinematics(dx, dy, dz, d, delta, ri, rj, mass[i], mass[j], v[i, 0],
                              v[i, 1], v[i, 2], v[j, 0] + ux, v[j, 1] + uy, v[j, 2] + uz,
                              omega[i, 0], omega[i, 1], omega[i, 2], omega[j, 0],
                              omega[j, 1], omega[j, 2])


@njit(cache=True, inline="always")
def pair_kinematics(x, v, omega, radius, mass, i, j):
    """Kinematics of pair (i, j) from arrays x, v, omega (n, 3), radius, mass (n,).

    Returns (nx, ny, nz, delta, reff, meff, vn, vtx, vty, vtz, arm_i, arm_j) with
    reff = r_i r_j/(r_i + r_j) [m] and meff = m_i m_j/(m_i + m_j) [kg]."""
    return _branch_kinematics(v, omega, radius, mass, i, j, x[j, 0] - x[i, 0],
                              x[j, 1] - x[i, 1], x[j, 2] - x[i, 2], 0.0, 0.0, 0.0)


@njit(cache=True, inline="always")
def periodic_pair_kinematics(x, v, omega, radius, mass, i, j, h, lg, ix, iy, iz):
    """`pair_kinematics` of i with the image x_j + h (ix, iy, iz) of j in a periodic cell
    with column vectors h (3, 3) [m] deforming at the velocity gradient lg (3, 3) [1/s].
    v holds fluctuations about the affine field L x, so the image of j moves, relative to
    i, at L d on top of v_j - v_i (the velocity jump across the cell is L h (ix, iy, iz))."""
    dx = x[j, 0] - x[i, 0] + h[0, 0] * ix + h[0, 1] * iy + h[0, 2] * iz
    dy = x[j, 1] - x[i, 1] + h[1, 0] * ix + h[1, 1] * iy + h[1, 2] * iz
    dz = x[j, 2] - x[i, 2] + h[2, 0] * ix + h[2, 1] * iy + h[2, 2] * iz
    ux = lg[0, 0] * dx + lg[0, 1] * dy + lg[0, 2] * dz
    uy = lg[1, 0] * dx + lg[1, 1] * dy + lg[1, 2] * dz
    uz = lg[2, 0] * dx + lg[2, 1] * dy + lg[2, 2] * dz
    return _branch_kinematics(v, omega, radius, mass, i, j, dx, dy, dz, ux, uy, uz)


@njit(cache=True, inline="always")
def wall_contact_kinematics(delta, ri, mi, wx, wy, wz, vix, viy, viz, ux, uy, uz, oix, oiy,
                            oiz):
    """Kinematics of particle i (radius, mass, velocity, spin) touching (delta > 0) a wall
    with inward unit normal w moving at u [m/s], from scalars only (see
    `contact_kinematics`). Same return layout as `wall_kinematics`."""
    nx, ny, nz = -wx, -wy, -wz
    ai = ri - 0.5 * delta
    vn, vtx, vty, vtz = _relative(nx, ny, nz, vix, viy, viz, ux, uy, uz, ai * oix, ai * oiy,
                                  ai * oiz)
    return nx, ny, nz, delta, ri, mi, vn, vtx, vty, vtz, ai, 0.0


@njit(cache=True, inline="always")
def wall_delta(x, radius, i, wall_p, wall_n, w):
    """Overlap r_i - distance of particle i with plane w [m] (> 0 touching)."""
    return radius[i] - ((x[i, 0] - wall_p[w, 0]) * wall_n[w, 0]
                        + (x[i, 1] - wall_p[w, 1]) * wall_n[w, 1]
                        + (x[i, 2] - wall_p[w, 2]) * wall_n[w, 2])


@njit(cache=True, inline="always")
def wall_kinematics(x, v, omega, radius, mass, i, wall_p, wall_n, wall_u, w):
    """Kinematics of particle i against plane w through wall_p[w] (3,) with unit normal
    wall_n[w] pointing into the domain, moving with velocity wall_u[w] [m/s]. Wall =
    infinite mass and radius: reff = r_i, meff = m_i (LIGGGHTS/LAMMPS). Same return layout
    as `pair_kinematics` (arm_j = 0). Row indices, not row slices, are passed: slices would
    cost reference counting per call."""
    delta = wall_delta(x, radius, i, wall_p, wall_n, w)
    if delta <= 0.0:
        return 0.0, 0.0, 0.0, delta, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    return wall_contact_kinematics(delta, radius[i], mass[i], wall_n[w, 0], wall_n[w, 1],
                                   wall_n[w, 2], v[i, 0], v[i, 1], v[i, 2], wall_u[w, 0],
                                   wall_u[w, 1], wall_u[w, 2], omega[i, 0], omega[i, 1],
                                   omega[i, 2])


@njit(cache=True, inline="always")
def project_history(sx, sy, sz, nx, ny, nz):
    """Project the tangential spring (m) onto the current tangent plane (LIGGGHTS)."""
    sn = sx * nx + sy * ny + sz * nz
    return sx - sn * nx, sy - sn * ny, sz - sn * nz


@njit(cache=True, inline="always")
def coulomb_tangential(kt, gt, mus, mud, fn, vtx, vty, vtz, sx, sy, sz, slip, dt):
    """Tangential spring-dashpot with static/dynamic Coulomb limit (seed 003 eq. 6).

    The spring s [m] integrates vt; trial force kt s + gt vt. Sticking contacts are
    limited by mus |fn|; once sliding (slip = 1) by mud |fn| until the trial force falls
    below it. When the limit is hit the force becomes mud |fn| along the trial force and
    the spring is reset to carry it alone (LAMMPS: the *total* tangential force is capped;
    LIGGGHTS caps the spring only, so its dashpot can exceed the Coulomb limit). Returns
    (ftx, fty, ftz, fdx, fdy, fdz, sx, sy, sz, slip, e_pre, e_t, p_fric): total force on j
    and its damping part [N] (the dashpot while sticking, zero while sliding: the Coulomb
    force is then friction), new spring, flag, spring energy before the increment (at the
    current kt) and after [J], sliding power ft . vt [W]."""
    e_pre = 0.5 * kt * (sx * sx + sy * sy + sz * sz)
    sx += vtx * dt
    sy += vty * dt
    sz += vtz * dt
    fsx, fsy, fsz = kt * sx, kt * sy, kt * sz
    fdx, fdy, fdz = gt * vtx, gt * vty, gt * vtz
    ftx, fty, ftz = fsx + fdx, fsy + fdy, fsz + fdz
    ft = math.sqrt(ftx * ftx + fty * fty + ftz * ftz)
    fc = max(fn, 0.0)  # no friction under a tensile (unclipped) normal force
    mu = mud if slip else mus
    p_fric = 0.0
    slip = 0
    if ft > mu * fc and ft > 0.0:
        scale = mud * fc / ft
        ftx, fty, ftz = ftx * scale, fty * scale, ftz * scale
        if kt > 0.0:
            sx, sy, sz = ftx / kt, fty / kt, ftz / kt
        p_fric = ftx * vtx + fty * vty + ftz * vtz
        fdx = fdy = fdz = 0.0  # sliding: the Coulomb force is friction, not damping
        slip = 1
    e_t = 0.5 * kt * (sx * sx + sy * sy + sz * sz)
    return ftx, fty, ftz, fdx, fdy, fdz, sx, sy, sz, slip, e_pre, e_t, p_fric
