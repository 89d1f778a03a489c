"""The energy ledger of a `Simulation`: the kernels of a step's works and the ledger's methods.

Every work is taken by the trapezoidal rule over the actual displacements: of the contacts
on the GHOST rows and on the walls, of external forces, of a periodic cell's affine motion
on the contacts (from the branch-force sums b (x) f of two force passes). The drift and the
kicks book the FREE particles' part (`dem.verlet`); `EnergyLedger._book` adds the rest a
step, `dem.fused_steps._steps` likewise inside its loop.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from dem.state import FREE

__all__ = ["EnergyLedger"]


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


class EnergyLedger:
    """The ledger's methods of `dem.integrate.Simulation` (a base of it: the arrays and sums
    they read are set up by `Simulation.__init__`; ``_led`` holds the sums over steps)."""

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
