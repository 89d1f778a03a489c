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
from dem.timestep import choose_dt, critical_dt
from dem.walls import WallSet

__all__ = ["Simulation", "kick", "kick_drift"]


@njit(parallel=True, cache=True)
def kick(v, omega, force, torque, mass, inertia, kind, g, h):
    """Half-kick of FREE particles by h [s]: v += h (F/m + g), omega += h T/I."""
    for i in prange(v.shape[0]):
        if kind[i] != 0:
            continue
        for c in range(3):
            v[i, c] += h * (force[i, c] / mass[i] + g[c])
            omega[i, c] += h * torque[i, c] / inertia[i]


@njit(parallel=True, cache=True)
def kick_drift(x, v, omega, force, torque, mass, inertia, kind, g, dt):
    """Half-kick by dt/2 then drift x += dt v, FREE particles only."""
    h = 0.5 * dt
    for i in prange(v.shape[0]):
        if kind[i] != 0:
            continue
        for c in range(3):
            v[i, c] += h * (force[i, c] / mass[i] + g[c])
            omega[i, c] += h * torque[i, c] / inertia[i]
            x[i, c] += dt * v[i, c]


class Simulation:
    """A DEM run: particles, contact materials, planar walls, gravity and a time step.

    Args:
        particles: `dem.state.Particles` (modified in place).
        materials: a `ContactMaterial` or a list indexed by ``particles.material``.
        walls: `dem.walls.PlaneWall` list. gravity: (3,) [m/s^2].
        dt: time step [s]; None: ``safety * critical_dt``; above critical raises
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
                 safety=0.2, force_dt=False, v_max=None, skin=None, domain=None,
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
        self._led = dict(damping=0.0, friction=0.0, walls=0.0, ghosts=0.0)
        self._pw = self.compute_forces()
        self._elastic = self._pw[0]
        self._e0 = self.kinetic_energy().sum() + self._elastic
        self._good = None
        self._check()

    # ---------------------------------------------------------------- forces
    def compute_forces(self, update_history: bool = True):
        """Contact forces at the current state into ``p.force``/``p.torque`` and
        ``walls.force``. Returns (elastic [J], damping power, friction power, wall power,
        ghost power [W]). ``update_history=False`` leaves the tangential springs untouched
        (re-evaluation inside a staggered coupling iteration)."""
        p, nl, w = self.p, self.nl, self.walls
        if nl.needs_rebuild(p.x, w.point):
            nl.build(p.x, p.radius, w.point, w.normal)
            self._check_domain()
        hist, slip, whist, wslip = nl.hist, nl.slip, nl.whist, nl.wslip
        if not update_history:
            hist, slip, whist, wslip = hist.copy(), slip.copy(), whist.copy(), wslip.copy()
        p.force[:] = 0.0
        p.torque[:] = 0.0
        out = np.empty((max(len(nl.pi), len(nl.wi)), NOUT))
        e1, d1, f1 = pair_forces(nl.pi, nl.pj, p.x, p.v, p.omega, p.radius, p.mass,
                                 p.material, self.table, hist, slip, self.dt, out,
                                 p.force, p.torque)
        e2, d2, f2, pw = wall_forces(nl.wi, nl.ww, p.x, p.v, p.omega, p.radius, p.mass,
                                     p.material, w.point, w.normal, w.velocity, w.material,
                                     self.table, whist, wslip, self.dt, out, p.force,
                                     p.torque, w.force)
        g = self._ghosts  # power of the prescribed ghosts on the free particles
        pg = -float((p.force[g] * p.v[g]).sum() + (p.torque[g] * p.omega[g]).sum())
        return e1 + e2, d1 + d2, f1 + f2, pw, pg

    # ---------------------------------------------------------------- stepping
    def step(self, n: int = 1):
        """Advance n steps of dt (velocity Verlet), with blow-up and domain checks."""
        p, dt = self.p, self.dt
        for _ in range(int(n)):
            kick_drift(p.x, p.v, p.omega, p.force, p.torque, p.mass, p.inertia, p.kind,
                       self.gravity, dt)
            self.walls.advance(dt)
            new = self.compute_forces()
            kick(p.v, p.omega, p.force, p.torque, p.mass, p.inertia, p.kind, self.gravity,
                 0.5 * dt)
            for k, name in ((1, "damping"), (2, "friction"), (3, "walls"), (4, "ghosts")):
                self._led[name] += 0.5 * dt * (self._pw[k] + new[k])
            self._pw, self._elastic = new, new[0]
            self.time += dt
            self.nsteps += 1
            if self.nsteps % self.check_every == 0:
                self._check()
        if self.nsteps % self.check_every:
            self._check()

    # ---------------------------------------------------------------- energy ledger
    def kinetic_energy(self) -> np.ndarray:
        """(translational, rotational) kinetic energy of FREE particles [J]."""
        p, f = self.p, self.p.kind == FREE
        return np.array([0.5 * (p.mass[f] * (p.v[f] ** 2).sum(1)).sum(),
                         0.5 * (p.inertia[f] * (p.omega[f] ** 2).sum(1)).sum()])

    def energy(self) -> dict:
        """Energy ledger [J]: kinetic, elastic, dissipated (damping, friction), work of
        gravity, walls and ghosts; ``balance`` = (kinetic + elastic + dissipated - work)
        minus its initial value, zero up to time discretisation."""
        p, f = self.p, self.p.kind == FREE
        kt, kr = self.kinetic_energy()
        wg = float((p.mass[f, None] * (p.x[f] - self._x0[f]) * self.gravity).sum())
        led = self._led
        stored = kt + kr + self._elastic + led["damping"] + led["friction"]
        work = wg + led["walls"] + led["ghosts"]
        return dict(kinetic_translational=kt, kinetic_rotational=kr, elastic=self._elastic,
                    dissipated_damping=led["damping"], dissipated_friction=led["friction"],
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
