"""The fused stepping loop: `Simulation.step`'s steps between two neighbour builds in one numba call.

`_steps` runs the kernels of `dem.verlet`, the compact-layout pair pass and the walls'
pass of `dem.forces`, the ledger's works of `dem.ledger`, a group drag and prescribed
motions in the order of `Simulation.step`'s Python loop (the same bits); the caller is
`dem.integrate.Simulation._fused`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from dem.drag import group_drag
from dem.forces import _pair_csr, _wall_all
from dem.ledger import _external_work, _gather_ghosts, _gather_rows, _ghost_work, _wall_work
from dem.prescribed import _prescribe
from dem.response import linear_response
from dem.verlet import _add_external, _drift, _kick, _kick_drift

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
           dsu, dout, resp, rsp, pause_every, sums, sum_rows, sum_out, presc, pr_rows, pr_group, pr_base, pr_a, pr_b,
           pr_vel, pr_om, pr_setom, pr_coef, gh, gprev, gnow, xg_at, xg_now, st, ist):
    """Steps s, s + 1, ... of a `Simulation.step` call of n steps, until n are done, a
    blow-up check is due (after the step that ends on a multiple of check_every: its second
    half-kick is `_kick`, the next drift is left to the next call) or the neighbour list
    needs a rebuild before a force pass (then that step's drift is done and pending, and
    the caller does the rest of the step). Pairs over the compact layout (start, pj32,
    live: `dem.forces.pair_layout`), walls (points wp advanced by dt wu, resultants wf,
    last ones wf_prev, points at the last pass wp_at, wforce = the walls' force rows),
    external forces if ext (rows erows, forces ef, positions at the last pass ex0), a
    group drag if drag (`dem.drag.GroupDrag`'s arrays, applied where `step` applies it),
    a linear response if resp (rsp: `dem.response.LinearResponse.arrays`, applied after the
    drag), a pause after every pause_every-th step of the call (> 0: the step ends with
    `_kick` and the call returns, as for a check), the force rows sum_rows added to sum_out
    (k, 3) after every force pass if sums (after the response),
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
        if resp:
            linear_response(x, force, kind, hit, *rsp)
        if sums:
            for k in range(sum_rows.shape[0]):
                for c in range(3):
                    sum_out[k, c] += force[sum_rows[k], c]
        e = e1 + e2
        es = s1 + s2
        final = s == n - 1 or (nsteps + 1) % check_every == 0 or (
            pause_every > 0 and (s + 1) % pause_every == 0)
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
