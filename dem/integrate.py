"""Velocity Verlet with rotations, and `Simulation`: particles + materials + walls + gravity.

One step (half-kick / drift / force / half-kick): v += dt/2 a, w += dt/2 T/I; x += dt v;
forces at the new positions; v += dt/2 a, w += dt/2 T/I. Only FREE particles move; GHOST
particles keep the x, v, omega written from outside (their contact forces are still in
``force``/``torque``); FIXED particles never move. Gravity enters the acceleration, not
``force``, so ``force`` holds contact forces only (what the coupling layer reads).
"""

from __future__ import annotations

import os

import numpy as np
from numba import njit, prange

from dem.contact import ContactMaterial, pair_table
from dem.errors import BlowUpError, DomainError
from dem.forces import NOUT, pair_forces, wall_forces
from dem.neighbours import NeighbourList
from dem.state import FREE, GHOST
from dem.timestep import DEFAULT_SAFETY, choose_dt, critical_dt
from dem.walls import WallSet

__all__ = ["Simulation", "kick"]

KICK_PARALLEL_MIN = 1_000_000  # particles; below this the kicks run on one thread


@njit(cache=True, inline="always")
def _kick_one(i, v, omega, force, torque, fd, td, mass, inertia, g, h, wd):
    """v += h (F/m + g), omega += h T/I for particle i; wd[i] = work of the dissipative
    parts (fd, td) in this kick, exact for the kinetic energy: h f . (u_old + u_new)/2."""
    w = 0.0
    for c in range(3):
        u0 = v[i, c]
        v[i, c] = u0 + h * (force[i, c] / mass[i] + g[c])
        o0 = omega[i, c]
        omega[i, c] = o0 + h * torque[i, c] / inertia[i]
        w += 0.5 * h * (fd[i, c] * (u0 + v[i, c]) + td[i, c] * (o0 + omega[i, c]))
    wd[i] = w


@njit(parallel=True, cache=True)
def _kick_par(x, v, omega, force, torque, fd, td, mass, inertia, kind, g, h, dt, wd):
    for i in prange(v.shape[0]):
        wd[i] = 0.0
        if kind[i] == 0:
            _kick_one(i, v, omega, force, torque, fd, td, mass, inertia, g, h, wd)
            for c in range(3):
                x[i, c] += dt * v[i, c]
        if dt > 0.0:  # drift kick: the forces are used up, clear them for the next pass
            for c in range(3):
                force[i, c] = torque[i, c] = fd[i, c] = td[i, c] = 0.0


@njit(cache=True)
def _kick_ser(x, v, omega, force, torque, fd, td, mass, inertia, kind, g, h, dt, wd):
    for i in range(v.shape[0]):
        wd[i] = 0.0
        if kind[i] == 0:
            _kick_one(i, v, omega, force, torque, fd, td, mass, inertia, g, h, wd)
            for c in range(3):
                x[i, c] += dt * v[i, c]
        if dt > 0.0:  # drift kick: the forces are used up, clear them for the next pass
            for c in range(3):
                force[i, c] = torque[i, c] = fd[i, c] = td[i, c] = 0.0


def kick(p, fd, td, g, h, drift_dt, wd) -> float:
    """Half-kick of FREE particles of `Particles` p by h [s] then drift x += drift_dt v
    (drift_dt = 0: kick only; drift_dt > 0 also zeroes force, torque, fd, td after use).
    fd, td (n, 3): dissipative parts of force and torque; wd (n,) scratch. Returns the
    work of the dissipative forces in this kick [J]."""
    # serial on purpose: a kick is memory-bound and a parallel region costs a thread
    # rendezvous, which on a loaded 2-core machine is worth more than the kick itself
    kern = _kick_par if p.n >= KICK_PARALLEL_MIN else _kick_ser
    kern(p.x, p.v, p.omega, p.force, p.torque, fd, td, p.mass, p.inertia, p.kind, g, h,
         drift_dt, wd)
    return float(wd.sum())


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
            ``./dem_last_good_state.npz``).
    """

    def __init__(self, particles, materials, walls=(), gravity=(0.0, 0.0, 0.0), dt=None, *,
                 safety=None, force_dt=False, v_max=None, skin=None, domain=None,
                 allow_overlap=False, blowup_factor=10.0, check_every=100, state_path=None):
        self.p = particles
        mats = [materials] if isinstance(materials, ContactMaterial) else list(materials)
        if particles.material.max(initial=0) >= len(mats):
            raise ValueError(f"particles.material refers to material "
                             f"{particles.material.max()} but only {len(mats)} given")
        self.materials, self.table = mats, pair_table(mats)
        self.walls = WallSet(walls)
        if len(self.walls) and self.walls.material.max() >= len(mats):
            raise ValueError("a PlaneWall.material index is beyond the material list")
        self.gravity = np.asarray(gravity, float).reshape(3)
        if particles.dim == 2 and self.gravity[2] != 0:
            raise ValueError("gravity[2] must be 0 for 2D disks")
        self.dt_crit = critical_dt(particles, mats, v_max)
        if safety is None:
            safety = DEFAULT_SAFETY[mats[0].law]
        self.dt = choose_dt(dt, self.dt_crit, safety, force_dt)
        skin = 0.2 * float(particles.radius.max()) if skin is None else float(skin)
        self.nl = NeighbourList(particles.n, skin)
        self.domain = None if domain is None else np.asarray(domain, float).reshape(2, 3)
        self.blowup_factor, self.check_every = float(blowup_factor), int(check_every)
        self.state_path = state_path or os.path.join(os.getcwd(), "dem_last_good_state.npz")
        particles.check_overlaps(allow=allow_overlap)
        self.time, self.nsteps = 0.0, 0
        self._ghosts = np.flatnonzero(particles.kind == GHOST)
        self._x0 = particles.x.copy()
        self._led = dict(dissipated=0.0, friction=0.0, walls=0.0, ghosts=0.0)
        self._fd, self._td = np.zeros((particles.n, 3)), np.zeros((particles.n, 3))
        self._wd, self._out = np.zeros(particles.n), np.empty((0, NOUT))
        self._zeroed = False
        self._elastic, _, _, pw, pg = self.compute_forces()
        self._pw = (pw, pg)
        self._e0 = self.kinetic_energy().sum() + self._elastic
        self._good = None
        self._check()

    # ---------------------------------------------------------------- forces
    def compute_forces(self, update_history: bool = True):
        """Contact forces at the current state into ``p.force``/``p.torque`` and
        ``walls.force``. Returns (elastic energy [J], tangential spring loss [J], friction
        dissipation estimate [J], wall power [W], ghost power [W]). ``update_history=False`` leaves the contact history
        untouched (re-evaluation inside a staggered coupling iteration)."""
        p, nl, w = self.p, self.nl, self.walls
        if nl.needs_rebuild(p.x, w.point):
            nl.build(p.x, p.radius, w.point, w.normal)
            self._check_domain()
        h = [nl.hist, nl.slip, nl.etan, nl.whist, nl.wslip, nl.wetan]
        if not update_history:
            h = [a.copy() for a in h]
        if not self._zeroed:
            for a in (p.force, p.torque, self._fd, self._td):
                a[:] = 0.0
        self._zeroed = False
        m = max(len(nl.pi), len(nl.wi))
        if self._out.shape[0] < m:
            self._out = np.empty((int(1.2 * m) + 16, NOUT))
        e1, l1, f1 = pair_forces(nl.pi, nl.pj, p.x, p.v, p.omega, p.radius, p.mass, p.material,
                             self.table, h[0], h[1], h[2], self.dt, self._out, p.force,
                             p.torque, self._fd, self._td)
        e2, l2, f2, pw = wall_forces(nl.wi, nl.ww, p.x, p.v, p.omega, p.radius, p.mass,
                                 p.material, w.point, w.normal, w.velocity, w.material,
                                 self.table, h[3], h[4], h[5], self.dt, self._out, p.force,
                                 p.torque, self._fd, self._td, w.force)
        g = self._ghosts  # power of the prescribed ghosts on the free particles
        pg = -float((p.force[g] * p.v[g]).sum() + (p.torque[g] * p.omega[g]).sum()) \
            if len(g) else 0.0
        return e1 + e2, l1 + l2, f1 + f2, pw, pg

    # ---------------------------------------------------------------- stepping
    def step(self, n: int = 1):
        """Advance n steps of dt (velocity Verlet), with blow-up and domain checks."""
        p, dt, led = self.p, self.dt, self._led
        for _ in range(int(n)):
            led["dissipated"] -= kick(p, self._fd, self._td, self.gravity, 0.5 * dt, dt,
                                      self._wd)
            self.walls.advance(dt)
            self._zeroed = True  # the drift kick cleared the force arrays
            e, loss, fric, pw, pg = self.compute_forces()
            led["dissipated"] += loss - kick(p, self._fd, self._td, self.gravity, 0.5 * dt,
                                             0.0, self._wd)
            led["friction"] += fric
            led["walls"] += 0.5 * dt * (self._pw[0] + pw)
            led["ghosts"] += 0.5 * dt * (self._pw[1] + pg)
            self._pw, self._elastic = (pw, pg), e
            self.time += dt
            self.nsteps += 1
            if self.nsteps % self.check_every == 0:
                self._check()
        if self.nsteps % self.check_every:
            self._check()

    def contact_forces(self, skip_ghost_pairs: bool = True):
        """Touching pairs (m, 2) and the force on i by j (m, 3) [N] now.

        The pair loop is evaluated again on copies of the contact history (the run keeps
        no per-contact forces), so calling this changes nothing. Pairs of two GHOST
        particles (a rigid clump's own contacts) are left out by default.
        """
        from dem.forces import NOUT, pair_forces

        p, nl = self.p, self.nl
        out = np.zeros((max(len(nl.pi), 1), NOUT))
        scratch = [np.zeros_like(p.force) for _ in range(4)]
        pair_forces(nl.pi, nl.pj, p.x, p.v, p.omega, p.radius, p.mass, p.material, self.table,
                    nl.hist.copy(), nl.slip.copy(), nl.etan.copy(), self.dt, out, *scratch)
        d = np.linalg.norm(p.x[nl.pj] - p.x[nl.pi], axis=1)
        keep = d < p.radius[nl.pi] + p.radius[nl.pj]
        if skip_ghost_pairs:
            keep &= ~((p.kind[nl.pi] == GHOST) & (p.kind[nl.pj] == GHOST))
        return np.stack([nl.pi[keep], nl.pj[keep]], axis=1), -out[: len(nl.pi)][keep, :3]

    # ---------------------------------------------------------------- energy ledger
    def kinetic_energy(self) -> np.ndarray:
        """(translational, rotational) kinetic energy of FREE particles [J]."""
        p, f = self.p, self.p.kind == FREE
        return np.array([0.5 * (p.mass[f] * (p.v[f] ** 2).sum(1)).sum(),
                         0.5 * (p.inertia[f] * (p.omega[f] ** 2).sum(1)).sum()])

    def energy(self) -> dict:
        """Energy ledger [J] of the FREE particles: kinetic, elastic (contacts), dissipated
        (exact work of the dissipative forces in the Verlet kicks plus the energy the
        tangential springs lose without work), split into friction (sliding power x dt,
        rolling resistance, spring losses) and damping (the rest: dashpots and clipping),
        work of gravity, moving walls and ghosts; ``balance`` = kinetic + elastic +
        dissipated - work - initial, zero up to the time discretisation error of the
        conservative forces."""
        p, f = self.p, self.p.kind == FREE
        kt, kr = self.kinetic_energy()
        wg = float((p.mass[f, None] * (p.x[f] - self._x0[f]) * self.gravity).sum())
        led = self._led
        stored = kt + kr + self._elastic + led["dissipated"]
        work = wg + led["walls"] + led["ghosts"]
        return dict(kinetic_translational=kt, kinetic_rotational=kr, elastic=self._elastic,
                    dissipated_damping=led["dissipated"] - led["friction"],
                    dissipated_friction=led["friction"],
                    work_gravity=wg, work_walls=led["walls"], work_ghosts=led["ghosts"],
                    initial=self._e0, balance=stored - work - self._e0)

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
        p = self.p
        ok = all(np.isfinite(a).all() for a in (p.x, p.v, p.omega))
        if ok:
            e = self.energy()
            ke = e["kinetic_translational"] + e["kinetic_rotational"]
            budget = (self._e0 + abs(e["work_gravity"]) + abs(e["work_walls"])
                      + abs(e["work_ghosts"]))
            ok = ke <= self.blowup_factor * budget + 1e-300
        if not ok:
            why = "NaN in x, v or omega" if not np.isfinite(p.v).all() else "kinetic energy jump"
            if self._good is not None:
                np.savez(self.state_path, **self._good)
            raise BlowUpError(f"blow-up ({why}) at step {self.nsteps}, t = {self.time:.6g} s "
                              f"(dt = {self.dt:.4g} s); last good state written to "
                              f"{self.state_path}", self.state_path)
        self._check_domain()
        self._good = dict(p.state_dict(), time=self.time, step=self.nsteps)

    def contacts(self):
        """(i, j) (k,) int64 of touching particle pairs now."""
        nl, x, r = self.nl, self.p.x, self.p.radius
        d = np.linalg.norm(x[nl.pj] - x[nl.pi], axis=1)
        t = d < r[nl.pi] + r[nl.pj]
        return nl.pi[t], nl.pj[t]
