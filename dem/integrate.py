"""`Simulation`: particles + materials + walls + gravity, stepped by velocity Verlet with rotations.

One step (half-kick / drift / force / half-kick, the kernels of `dem.verlet`): v += dt/2 a,
w += dt/2 T/I; x += dt v; forces at the new positions; v += dt/2 a, w += dt/2 T/I. Only FREE
particles move; GHOST particles keep the x, v, omega written from outside (their contact
forces are still in ``force``/``torque``); FIXED particles never move. Gravity enters the
acceleration, not ``force``, so ``force`` holds contact forces only (what the coupling layer
reads). Without a hook the steps run in one numba call (`dem.fused_steps`); the energy
ledger is `dem.ledger`'s, the exact state `dem.simulation_state`'s.
"""

from __future__ import annotations

import os
import tempfile

import numpy as np
from numba import get_num_threads

from dem.contact import ContactMaterial, pair_table
from dem.errors import BlowUpError, DomainError, OverlapError
from dem.forces import (
    NO_CELL,
    NOUT,
    PARALLEL_MIN,
    WALL_PARALLEL_MIN,
    pair_forces,
    pair_layout,
    refresh_live,
    wall_forces,
)
from dem.fused_steps import LED_KEYS, _steps
from dem.ledger import EnergyLedger, _branch_force_sums, _gather_ghosts, _gather_rows, _kinetic_finite
from dem.neighbours import NeighbourList
from dem.prescribed import _prescribe
from dem.simulation_state import _STATE_KEYS, SimulationState
from dem.state import FREE, GHOST
from dem.timestep import DEFAULT_SAFETY, choose_dt, critical_dt
from dem.verlet import _add_external, _damp, _drift, _kick, _kick_drift, _kick_drift_par
from dem.walls import WallSet

__all__ = ["Simulation"]

_NO_L, _NO_O, _EMPTY = np.zeros((3, 3)), np.zeros(3), np.zeros((0, 3))
_NO_DRAG = (False, np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(3),
            np.zeros(0), _EMPTY, _EMPTY, _EMPTY)   # the types of `GroupDrag.arrays`
_I0, _F0 = np.zeros(0, np.int64), np.zeros(0)
_I32 = np.zeros(0, np.int32)
_I2, _F2 = np.zeros((0, 1), np.int64), np.zeros((0, 1))
_NO_RESPONSE = (_I0, np.zeros((0, 2)), _I2, _F2, _F2, _I0, _I32, _F0, _F0, _I0, _I32, _F0, _I0,
                _I32, _F0, _F0, _I0, _I0, _I0, _I32, _F0, np.zeros(1, np.int64), _F0, _F0, _F0,
                _F0, _F0, _F0, _EMPTY)
"""The types of `dem.response.LinearResponse.arrays`."""
_NO_PK = (np.zeros(0, np.int64), np.zeros(0, np.int64), _EMPTY, _EMPTY, _EMPTY, _EMPTY, _EMPTY,
          np.zeros(0, np.bool_), np.zeros((1, 1, 2)))
"""`dem.prescribed.Prescribed.pack` of no motion (the types `_steps` takes)."""
_NO_SUMS = (np.zeros(0, np.int64), _EMPTY)   # `Simulation.step`'s sums: rows, out

KD_PARALLEL_MIN = 4096
"""Particles from which, with more than one numba thread, `_kick_drift_par` runs (below, a
thread rendezvous costs more than the pass; see `dem.forces.PARALLEL_MIN`)."""


def _pause_every(every, pause) -> int:
    every = int(every) if pause is not None else 0
    if every < 0:
        raise ValueError(f"Simulation.step: pause_every must be >= 0, got {every}")
    return every


def _sums(sums, n: int):
    """`Simulation.step`'s ``sums`` checked: (rows (k,) int64, out (k, 3) float64, written in
    place), or (None, None)."""
    if sums is None:
        return None, None
    rows, out = sums
    rows = np.asarray(rows)
    if rows.dtype != np.int64 or rows.ndim != 1 or (len(rows) and (rows.min() < 0 or rows.max() >= n)):
        raise ValueError(f"Simulation.step: sums' rows must be int64 indices in [0, {n}) (k,)")
    if not (isinstance(out, np.ndarray) and out.dtype == np.float64 and out.shape == (len(rows), 3)
            and out.flags.c_contiguous):
        raise ValueError(f"Simulation.step: sums' out must be a C-contiguous float64 array of "
                         f"shape ({len(rows)}, 3), written in place")
    return rows, out


def _apply(sim, *extras) -> None:
    """Apply a step's drag and response (those not None) after its force pass."""
    for extra in extras:
        if extra is not None:
            extra.apply(sim)


def _due(done: int, every: int) -> bool:
    """Whether a pause follows the step that makes ``done`` steps of the call."""
    return every > 0 and done % every == 0


class Simulation(EnergyLedger, SimulationState):
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
            ``<tempdir>/dem_last_good_state_<pid>.npz``, not the working directory: a
            library call should not litter it; the error names the file).
        cell: a `dem.periodic.PeriodicCell` (then ``p.v`` are fluctuations about the
            cell's affine velocity field; no walls, ghosts or domain box).
        prescribed_pairs: evaluate contacts between two particles that are not FREE (GHOST
            or FIXED). False skips them: they move no particle, and the force on a GHOST row
            is then what the FREE particles (and walls) exert on it, the reaction a
            partitioned coupling hands its continuum.
    """

    def __init__(self, particles, materials, walls=(), gravity=(0.0, 0.0, 0.0), dt=None, *,
                 safety=None, force_dt=False, v_max=None, skin=None, domain=None,
                 allow_overlap=False, blowup_factor=10.0, check_every=100, state_path=None,
                 cell=None, prescribed_pairs=True):
        self.p = particles
        self.prescribed_pairs = bool(prescribed_pairs)
        mats = [materials] if isinstance(materials, ContactMaterial) else list(materials)
        if particles.material.max(initial=0) >= len(mats):
            raise ValueError(f"particles.material refers to material "
                             f"{particles.material.max()} but only {len(mats)} given")
        self.materials, self.table = mats, pair_table(mats)
        self.walls = WallSet(walls)
        if len(self.walls) and self.walls.material.max() >= len(mats):
            raise ValueError("a PlaneWall.material index is beyond the material list")
        g = np.asarray(gravity, float)
        if particles.dim == 2 and g.shape == (2,):
            g = np.append(g, 0.0)
        if g.shape != (3,) or not np.isfinite(g).all():
            raise ValueError(f"gravity must be 3 finite numbers [m/s^2] (2 or 3 in 2D, z = 0), "
                             f"got {gravity!r}")
        self.gravity = g
        if particles.dim == 2 and self.gravity[2] != 0:
            raise ValueError("gravity[2] must be 0 for 2D disks")
        self.cell = cell
        if cell is not None:
            if cell.dim != particles.dim:
                raise ValueError(f"cell: a {cell.dim}D PeriodicCell for {particles.dim}D "
                                 f"particles")
            if len(self.walls) or domain is not None or (particles.kind == GHOST).any():
                raise ValueError("cell: a periodic cell takes no walls, domain box or GHOST "
                                 "particles")
        self.dt_crit = critical_dt(particles, mats, v_max)
        if safety is None:
            safety = DEFAULT_SAFETY[mats[0].law]
        self.dt = choose_dt(dt, self.dt_crit, safety, force_dt)
        skin = 0.2 * float(particles.radius.max()) if skin is None else float(skin)
        self.nl = NeighbourList(particles.n, skin)
        self.domain = None if domain is None else np.asarray(domain, float).reshape(2, 3)
        self.blowup_factor, self.check_every = float(blowup_factor), int(check_every)
        self.state_path = state_path or os.path.join(tempfile.gettempdir(),
                                                  f"dem_last_good_state_{os.getpid()}.npz")
        if cell is None and not allow_overlap:
            # round-off contacts (1e-9 of a radius) are not overlaps
            particles.check_overlaps(allow=allow_overlap, tol=1e-9 * float(particles.radius.max()))
        self.time, self.nsteps = 0.0, 0
        self.damping_removed = 0.0   # kinetic energy taken out by step(decay=...) [J]
        self._ghosts = self._ghost_index()
        n = particles.n
        self._led = dict(dissipated=0.0, friction=0.0, walls=0.0, ghosts=0.0, gravity=0.0,
                         cell=0.0, external=0.0)
        # constant external forces on FREE rows (`set_external_force`): (rows, forces, rows'
        # positions at the last force pass) or None
        self._ext = None
        # contact sums b (x) f (`_stress_sums`): of the last force pass, of the one before,
        # and of the last forces with the branch vectors of the pass before
        self._bf = self._bf_prev = self._bf_mixed = np.zeros((3, 3, 3))
        self._xh = None  # positions and cell vectors of the last force pass
        self._fe, self._fd, self._td = (np.zeros((n, 3)) for _ in range(3))
        self._hit = np.zeros(n, np.int8)  # particles with a contact in the last force pass
        self._lay = (None, None)  # ((pair arrays it was made from), dem.forces.pair_layout)
        self._wf = np.zeros((len(self.walls), 9))  # wall resultants: total, fe, fd [N]
        self._out = np.empty((0, NOUT))
        self._zeroed = False
        self._elastic, self._spring = self._evaluate(True)
        self._at, self._wf_prev = self._positions(), self._wf.copy()
        if cell is not None and self.nl.builds:
            self._check_cell_overlaps(allow_overlap)
        self._e0 = self.kinetic_energy().sum() + self._elastic
        self._shadow0 = self._shadow()
        self._good = None
        self._check()

    # ---------------------------------------------------------------- forces
    def _layout(self, fresh: bool):
        """`dem.forces.pair_layout` of the current pair list (None in a periodic cell or
        if the list is not sorted by i). Rebuilt when the list or its history arrays are
        new objects; with ``fresh`` its live flags are recomputed from the history (the
        arrays may have been written between two calls of `step`)."""
        nl = self.nl
        key = self._lay[0]
        if key is None or key[0] is not nl.pi or key[1] is not nl.hist or \
                key[2] is not nl.slip or key[3] is not nl.etan:
            lay = None
            if self.cell is None and len(nl.pi) and (len(nl.pi) < 2
                                                     or (nl.pi[1:] >= nl.pi[:-1]).all()):
                lay = pair_layout(nl.pi, nl.pj, self.p.n, nl.hist, nl.slip, nl.etan)
            self._lay = ((nl.pi, nl.hist, nl.slip, nl.etan), lay)
        elif fresh and self._lay[1] is not None:
            refresh_live(nl.hist, nl.slip, nl.etan, self._lay[1][2])
        return self._lay[1]

    def _evaluate(self, update_history: bool, disp2=None, fresh=True):
        """Contact forces now into p.force/p.torque, the private class arrays and the wall
        resultants. Returns (elastic energy, tangential spring energy) [J]. disp2: the
        largest squared displacement since the neighbour build if already known (drift);
        fresh: the contact history may have been changed from outside since the last
        force pass (False only between two steps of one `step` call)."""
        p, nl, w = self.p, self.nl, self.walls
        if nl.needs_rebuild(p.x, w.point, self.cell, disp2):
            nl.build(p.x, p.radius, w.point, w.normal, self.cell, skip=self._pair_skip())
            self._prune(nl)
            self._check_domain()
        h = [nl.hist, nl.slip, nl.etan, nl.whist, nl.wslip, nl.wetan]
        lay = None
        if update_history:
            lay = self._layout(fresh)
        else:
            h = [a.copy() for a in h]
        acc = (p.force, p.torque, self._fe, self._fd, self._td)
        # after a drift the velocities are half a step behind this pass: the dashpots
        # predict them at its instant (`dem.contact.damping`)
        horizon = 0.5 * self.dt if self._zeroed else 0.0
        if not self._zeroed:
            for a in acc:
                a[:] = 0.0
            self._hit[:] = 0
        self._zeroed = False
        m = max(len(nl.pi), len(nl.wi), 1)
        if self._out.shape[0] < m:
            self._out = np.empty((int(1.2 * m) + 16, NOUT))
        cell = NO_CELL if self.cell is None else self.cell.as_kernel_args(nl.img)
        # the cell's work needs the contacts' rows (the same bits as without them), at every
        # pass: the trapezoid of a step under a velocity gradient uses the pass before
        rows = self.cell is not None and update_history
        e1, s1 = pair_forces(nl.pi, nl.pj, p.x, p.v, p.omega, p.radius, p.mass, p.material,
                             self.table, h[0], h[1], h[2], self.dt, self._out, *acc, cell=cell,
                             hit=self._hit, layout=lay, rows=rows, horizon=horizon)
        if rows:
            self._bf_prev = self._bf
            self._bf, self._bf_mixed = self._stress_sums(len(nl.pi))
        e2, s2 = wall_forces(nl.wi, nl.ww, p.x, p.v, p.omega, p.radius, p.mass, p.material,
                             w.point, w.normal, w.velocity, w.table_columns(len(self.materials)),
                             self.table, h[3], h[4], h[5], self.dt, self._out, *acc, self._wf,
                             hit=self._hit, horizon=horizon)
        w.force[:] = self._wf[:, :3]
        if self._ext is not None:
            rows, f, _ = self._ext
            _add_external(rows, f, p.force, self._hit)
        return e1 + e2, s1 + s2

    def kinds_changed(self) -> None:
        """Call after writing ``p.kind`` from outside (grains held or released): the ledger
        books the ghosts' work over the new set of GHOST rows."""
        self._ghosts = self._ghost_index()
        self._at = self._positions()
        if self.walls.free_only.any() or not self.prescribed_pairs:
            # a released grain meets the free_only walls (and the prescribed rows) its GHOST
            # row was kept from
            self.rebuild_neighbours()

    @property
    def forced(self) -> np.ndarray:
        """(n,) int8 flags of the rows whose forces the kicks read (set by the force pass for
        every particle in contact, and for the rows of `set_external_force`); a step hook
        that adds a force to a row must set its flag, or a grain out of contact keeps the
        force in a row no kick reads (`dem.drag.GroupDrag`)."""
        return self._hit

    def external_force(self):
        """(rows (k,), forces (k, 3) [N]) of `set_external_force` (empty if none)."""
        if self._ext is None:
            return np.zeros(0, np.int64), np.zeros((0, 3))
        return self._ext[0], self._ext[1]

    def set_external_force(self, rows, force) -> None:
        """Apply the constant force ``force`` [N] ((k, 3), or (3,) for every row) to the FREE
        particles ``rows`` (k,) from the next force pass on, beside their contact forces and
        gravity: a surcharge or a membrane pressure on a specimen's boundary grains, a fluid
        drag; it is added to the forces now in the arrays, which the next half-kick uses.
        Its work is booked as ``work_external`` in `energy`. ``rows=None`` removes it.
        Not with a periodic cell (positions wrap)."""
        p = self.p
        if self._ext is not None:   # out of the forces now in the arrays
            p.force[self._ext[0]] -= self._ext[1]
        if rows is None:
            self._ext = None
            return
        rows = np.asarray(rows, np.int64).ravel()
        f = np.broadcast_to(np.asarray(force, float), (len(rows), 3)).copy()
        if self.cell is not None:
            raise ValueError("set_external_force: not in a periodic cell")
        if len(rows) and (rows.min() < 0 or rows.max() >= p.n):
            raise ValueError(f"set_external_force: rows must lie in [0, {p.n}), got "
                             f"{rows.min()}..{rows.max()}")
        # (a count, not np.unique: a fluid sets every grain's force each fluid step)
        if len(rows) and np.bincount(rows, minlength=p.n).max() > 1:
            raise ValueError("set_external_force: rows repeat")
        if (p.kind[rows] != FREE).any():
            raise ValueError("set_external_force: rows must be FREE particles (the others' "
                             "motion is prescribed)")
        if not np.isfinite(f).all():
            raise ValueError("set_external_force: force is not finite")
        if p.dim == 2 and (f[:, 2] != 0).any():
            raise ValueError("set_external_force: force[:, 2] must be 0 for 2D disks")
        self._ext = (rows, f, p.x[rows].copy())
        # into the forces now in the arrays, which the next half-kick uses
        p.force[rows] += f
        self._hit[rows] = 1

    def _stress_sums(self, m):
        """Sums over the touching pairs of b (x) f (3, 3, 3) [N m] for f the contact force
        on i by j, its conservative normal part and its damping part (the rows (m, NOUT) of
        the force pass just done), with b the branch vector from i to j's image now and
        with b as it was at the last force pass (the drift between moved the pair apart by
        dt L b there: the trapezoid of the cell's work needs that b). A particle wrapped
        into the cell since then is unwrapped by the whole cell vectors it jumped."""
        cell, nl, x = self.cell, self.nl, self.p.x
        x0, h0 = (x, cell.h) if self._xh is None else self._xh
        bf, bf0 = np.zeros((3, 3, 3)), np.zeros((3, 3, 3))
        _branch_force_sums(nl.pi, nl.pj, nl.img, self._out[:m], x, cell.h, x0, h0,
                           np.linalg.inv(cell.h), bf, bf0)
        self._xh = (x.copy(), cell.h.copy())
        return bf, bf0

    def rebuild_neighbours(self) -> None:
        """Build the neighbour list now (positions or radii changed from outside by more than
        the skin allows, e.g. grains grown in place); the contact history is carried."""
        self.nl.build(self.p.x, self.p.radius, self.walls.point, self.walls.normal, self.cell,
                      skip=self._pair_skip())
        self._prune(self.nl)

    def _pair_skip(self):
        """(n,) bool: the rows whose pairs among themselves the neighbour build leaves out
        (``prescribed_pairs = False``: the prescribed rows, by their own kinds), or None."""
        return None if self.prescribed_pairs else self._own_kinds() != FREE

    def _prune(self, nl):
        """Called after every neighbour build, before the force pass: drops the GHOST rows'
        candidates of ``free_only`` walls; a subclass may drop more (`dem.parallel` drops the
        halo copies' own contacts). (The pairs of two prescribed rows are not built at all
        under ``prescribed_pairs = False``: `_pair_skip`.)"""
        w = self.walls
        if len(nl.wi) and w.free_only.any():
            nl.keep_walls(~(w.free_only[nl.ww] & (self.p.kind[nl.wi] == GHOST)))

    def _own_kinds(self) -> np.ndarray:
        """(n,) the particles' own kinds, by which ``prescribed_pairs = False`` drops pairs
        (a subclass holding copies of other runs' particles gives theirs)."""
        return self.p.kind

    def compute_forces(self, update_history: bool = True):
        """Contact forces at the current state into ``p.force``/``p.torque`` and
        ``walls.force``. Returns (elastic energy [J], tangential spring energy [J], power
        of the damping forces on the FREE particles [W], wall power [W], ghost power [W]).
        ``update_history=False`` leaves the contact history untouched (re-evaluation inside
        a staggered coupling iteration)."""
        e, es = self._evaluate(update_history)
        p, w, g = self.p, self.walls, self._ghosts
        if update_history:
            self._elastic, self._spring = e, es
        self._at = self._positions()  # where the forces now in the arrays were evaluated
        f = p.kind == FREE
        pd = float((self._fd[f] * p.v[f]).sum() + (self._td[f] * p.omega[f]).sum())
        pw = -float((w.force * w.velocity).sum())
        pg = -float((p.force[g] * p.v[g]).sum() + (p.torque[g] * p.omega[g]).sum()) \
            if len(g) else 0.0
        return e, es, pd, pw, pg

    def _positions(self, out=None):
        """(positions of the GHOST rows (into ``out`` if given), wall points) now."""
        g = self._ghosts
        xg = _EMPTY if not len(g) else (self.p.x[g] if out is None else _gather_rows(g, self.p.x, out))
        return xg, (self.walls.point.copy() if len(self.walls) else _EMPTY)

    # ---------------------------------------------------------------- stepping
    def step(self, n: int = 1, hook=None, prescribed=None, decay: float | None = None,
             drag=None, response=None, pause_every: int = 0, pause=None, sums=None):
        """Advance n steps of dt (velocity Verlet), with blow-up and domain checks.

        Between two steps of one call (unless a check falls in between) the second
        half-kick and the next drift run as one pass over the particles (`_kick_drift`:
        the same bits as `_kick` then `_drift`), so a caller that needs to act between
        steps passes ``hook`` rather than calling ``step(1)`` n times: ``hook()`` runs after
        each step's force pass, before its second half-kick (forces new, v still the
        half-step velocity; it may write the rows of particles that are not FREE; ``sim.time``
        and ``sim.nsteps`` still hold the values before the step), and a true return ends the
        call after that step. ``prescribed``: a
        `dem.prescribed.Prescribed` whose motions of GHOST rows are written before each
        step's drift (the same bits as writing them from Python before each of n
        ``step(1)`` calls; ghosts' rotations are booked as dt omega, so a prescribed omega
        is constant over the call). ``decay``: the FREE particles' v and omega are scaled
        by it before each step's drift (mass-proportional damping, `dem.control.relax`), the
        kinetic energy it takes out booked as dissipated and summed in ``damping_removed``.
        ``drag``: a `dem.drag.GroupDrag` applied in every step where a hook would run
        (before ``hook``), in the fused loop too (a hook applying it costs the Python loop:
        +20-35 % a step at 0.5-2k grains). ``response``: a `dem.response.LinearResponse`
        applied after the drag, in the fused loop too. ``pause()`` runs between steps after
        every ``pause_every``-th step of the call (not after the last): the call's motions
        and loop go on after it, where a caller would otherwise split the call (a fluid step
        every few DEM steps, which may set external forces or a new response's reference);
        a true return ends the call there (`dem.parallel`'s halo exchange between the steps
        of its local runs: a stale halo ends the local call). ``sums``: a pair (rows (k,)
        int64, out (k, 3) float): after every force pass (and the response) the force rows
        ``rows`` are added to ``out``, in the fused loop too (a coupling's time-averaged
        reactions on its ghosts, which a hook would read at the Python loop's cost). Returns
        the number of steps done."""
        p, dt, cell = self.p, self.dt, self.cell
        sum_rows, sum_out = _sums(sums, p.n)
        pk = None if prescribed is None else prescribed.pack(int(n), dt, p.kind)
        h = 0.5 * dt
        per, lg, org = (0, _NO_L, _NO_O) if cell is None else \
            (1, cell.velocity_gradient, cell.origin)
        acc = (p.force, p.torque, self._fe, self._fd, self._td)
        prm = (p.mass, p.inertia, p.kind, self.gravity, h)
        ng = len(self._ghosts)
        ghosts = ng > 0
        # two buffers each for the ghosts' force rows and positions: a step's rows and
        # positions are the next step's "before" (no allocation per step)
        rowbuf = [np.empty((ng, 15)), np.empty((ng, 15))] if ghosts else None
        posbuf = [np.empty((ng, 3)), np.empty((ng, 3))] if ghosts else None
        res = np.empty(8)
        kd = _kick_drift_par if p.n >= KD_PARALLEL_MIN and get_num_threads() > 1 else _kick_drift
        n = int(n)
        pending = None  # (works of the old forces, largest squared displacement) of a drift
        gprev = None  # ghost rows of the forces the drift cleared
        fused = hook is None and decay is None and cell is None and self._plain_loop()
        pause_every = _pause_every(pause_every, pause)
        s = 0
        while s < n:
            if fused:  # as many steps as it can in one numba call (`_steps`)
                k, pending, gprev = self._fused(s, n, pending, pk, gprev, drag, response,
                                                pause_every, None if sums is None else (sum_rows, sum_out))
                s += k
                if k and self.nsteps % self.check_every == 0:
                    self._check()
                if s == n:
                    break
                if k and pending is None and _due(s, pause_every) and pause():
                    n = s
                    break
                if k and pending is None:
                    continue
                # a neighbour build is due before this step's force pass (its drift
                # pending), or the serial drivers do not apply: the step below
            if pending is None:
                if decay is not None:
                    removed = _damp(p.v, p.omega, p.mass, p.inertia, p.kind, decay)
                    self.damping_removed += removed
                    self._led["dissipated"] += removed
                if pk is not None:
                    _prescribe(s, *pk, p.x, p.v, p.omega)
                if ghosts and gprev is None:  # (else the last step's: the kick keeps forces)
                    gprev = self._ghost_rows(rowbuf[0])
                pending = _drift(p.x, p.v, p.omega, *acc, *prm, dt, per, lg, org,
                                 self._x0_tracked(), self._hit)
            wc0, we0, wd0, d2 = pending
            self.walls.advance(dt)
            if cell is not None:
                cell.advance(dt)
            self._zeroed = True  # the drift cleared the force arrays
            self._wf_prev[:] = self._wf
            e, es = self._evaluate(True, d2 if cell is None else None, s == 0)
            gnow = self._ghost_rows(rowbuf[1] if gprev is rowbuf[0] else rowbuf[0]) if ghosts else None
            _apply(self, drag, response)
            if sums is not None:
                sum_out += p.force[sum_rows]
            last = hook is not None and bool(hook())
            if len(self._ghosts) != ng:   # the buffers (and the numba gathers) are sized for ng
                raise RuntimeError("Simulation.step: the hook changed the set of GHOST rows; "
                                   "change kinds between step calls")
            # of this force pass (before the next step's motions)
            now = self._positions(posbuf[s % 2] if ghosts else None)
            paused = _due(s + 1, pause_every)
            if (last or s == n - 1 or (self.nsteps + 1) % self.check_every == 0 or decay is not None
                    or paused):
                wc1, we1, wd1, wg = _kick(p.v, p.omega, *acc, *prm, self._hit)
                pending = None
            else:
                if pk is not None:  # the next step's motions, before its drift (in kd)
                    _prescribe(s + 1, *pk, p.x, p.v, p.omega)
                kd(p.x, p.v, p.omega, *acc, *prm, dt, per, lg, org, self._x0_tracked(),
                   self._hit, res)
                wc1, we1, wd1, wg = res[0], res[1], res[2], res[3]
                pending = (res[4], res[5], res[6], res[7])
            self._book(wc0 + wc1, we0 + we1, wd0 + wd1, wg, e, es, gprev, gnow, now)
            gprev = gnow
            self.time += dt
            self.nsteps += 1
            if self.nsteps % self.check_every == 0:
                self._check()
            s += 1
            if last:
                n = s
                break
            if paused and s < n and pause():
                n = s
                break
        if self.nsteps % self.check_every:
            self._check()
        return n

    _LOOP_METHODS = ("_evaluate", "_book", "_positions", "_ghost_rows", "_x0_tracked")

    def _plain_loop(self) -> bool:
        """Whether the step loop's methods are this class's (a subclass that changes one of
        them keeps the Python loop: `_steps` does what these do here)."""
        cls = type(self)
        return all(getattr(cls, m) is getattr(Simulation, m) for m in self._LOOP_METHODS)

    def _fused(self, s, n, pending, pk, gprev, drag=None, response=None, pause_every=0,
               sums=None):
        """Steps s, s + 1, ... of a `step` call of n steps in `_steps` (no hook, damping or
        cell: the caller checks), if the serial drivers are the ones `_evaluate` would run.
        pk: the packed prescribed motions or None; gprev: the GHOST rows' forces of the
        last force pass (None: not gathered yet in this call). Returns (steps done, the
        pending drift's values or None, gprev); (0, pending, gprev) if it did not apply."""
        p, nl, w = self.p, self.nl, self.walls
        if nl._x0 is None or nl._x0.shape != p.x.shape or (len(w) and nl._wp0 is None):
            return 0, pending, gprev
        if (p.n >= KD_PARALLEL_MIN or len(nl.pi) >= PARALLEL_MIN
                or len(nl.wi) >= WALL_PARALLEL_MIN) and get_num_threads() > 1:
            return 0, pending, gprev
        lay = self._layout(s == 0)
        if lay is None:
            if len(nl.pi):  # not sorted by i: `pair_forces` takes the plain loop
                return 0, pending, gprev
            lay = (np.zeros(p.n + 1, np.int64), np.zeros(0, np.int32), np.zeros(0, np.int8))
        led = self._led
        st = np.array([self.time, self._elastic, self._spring, 0.0, 0.0, 0.0, 0.0]
                      + [led[k] for k in LED_KEYS])
        if pending is not None:
            st[3:7] = pending
        ist = np.array([self.nsteps, pending is not None, 0, gprev is not None], np.int64)
        ext = self._ext is not None
        erows, ef, ex0 = self._ext if ext else (np.zeros(0, np.int64), _EMPTY, _EMPTY)
        nw = len(w)
        wp_at = np.array(self._at[1], float).reshape(nw, 3) if nw else _EMPTY
        gh = self._ghosts
        ng = len(gh)
        gbuf = np.empty((ng, 15)) if gprev is None else np.array(gprev)
        xg_at = np.array(self._at[0], float).reshape(ng, 3)
        _steps(s, n, self.check_every, p.x, p.v, p.omega, p.force, p.torque, self._fe,
               self._fd, self._td, p.mass, p.inertia, p.kind, self.gravity, 0.5 * self.dt,
               self.dt, nl._x0, self._hit, p.radius, p.material, self.table, lay[0], lay[1],
               lay[2], nl.hist, nl.slip, nl.etan, nl.wi, nl.ww, w.point, w.normal,
               w.velocity, w.table_columns(len(self.materials)), nl.whist, nl.wslip,
               nl.wetan, self._wf, self._wf_prev, wp_at, w.force,
               nl._wp0 if nw else _EMPTY, nl.skin, ext, erows, ef, ex0,
               *(_NO_DRAG if drag is None else (True, *drag.arrays(self))),
               response is not None, _NO_RESPONSE if response is None else response.arrays(),
               pause_every, sums is not None, *(_NO_SUMS if sums is None else sums), pk is not None,
               *(_NO_PK if pk is None else pk), gh, gbuf, np.empty((ng, 15)), xg_at,
               np.empty((ng, 3)), st, ist)
        done = int(ist[2])
        self.time, self.nsteps = float(st[0]), int(ist[0])
        for q, k in enumerate(LED_KEYS):
            led[k] = float(st[7 + q])
        if done:
            self._elastic, self._spring = float(st[1]), float(st[2])
            self._at = (xg_at if ng else self._at[0], wp_at if nw else self._at[1])
            self._zeroed = False
        return (done, tuple(float(a) for a in st[3:7]) if ist[1] else None,
                gbuf if ist[3] else None)

    def _x0_tracked(self):
        """Build positions of the neighbour list for the drift to measure displacements
        from (empty: not measured, in a periodic cell or before the first build)."""
        x0 = self.nl._x0
        if self.cell is not None or x0 is None or x0.shape != self.p.x.shape:
            return _EMPTY
        return x0

    def _ghost_rows(self, out):
        """(ng, 15) force, torque, fe, fd, td of the GHOST particles now, into ``out``."""
        p = self.p
        return _gather_ghosts(self._ghosts, p.force, p.torque, self._fe, self._fd, self._td, out)

    def _branches(self):
        """Branch vectors (m, 3) [m] from i to (the nearest image of) j of the listed pairs."""
        p, nl = self.p, self.nl
        d = p.x[nl.pj] - p.x[nl.pi]
        if self.cell is not None:
            d += nl.img @ self.cell.h.T
        return d

    def contact_forces(self, skip_ghost_pairs: bool = True, return_branch: bool = False):
        """Touching pairs (m, 2) and the force on i by j (m, 3) [N] now (and, if
        ``return_branch``, the branch vectors (m, 3) [m] from i to j's image).

        The pair loop is evaluated again on copies of the contact history (the run keeps
        no per-contact forces), so calling this changes nothing. Pairs of two GHOST
        particles (a rigid clump's own contacts) are left out by default.
        """
        p, nl = self.p, self.nl
        out = np.zeros((max(len(nl.pi), 1), NOUT))
        scratch = [np.zeros_like(p.force) for _ in range(5)]
        cell = NO_CELL if self.cell is None else self.cell.as_kernel_args(nl.img)
        pair_forces(nl.pi, nl.pj, p.x, p.v, p.omega, p.radius, p.mass, p.material, self.table,
                    nl.hist.copy(), nl.slip.copy(), nl.etan.copy(), self.dt, out, *scratch,
                    cell=cell, rows=True)
        b = self._branches()
        keep = np.linalg.norm(b, axis=1) < p.radius[nl.pi] + p.radius[nl.pj]
        if skip_ghost_pairs:
            keep &= ~((p.kind[nl.pi] == GHOST) & (p.kind[nl.pj] == GHOST))
        res = np.stack([nl.pi[keep], nl.pj[keep]], axis=1), -out[: len(nl.pi)][keep, :3]
        return res + (b[keep],) if return_branch else res


    def force_parts(self):
        """(fe, fd, td) (n, 3) [N, N, N m]: the conservative normal and the damping parts of
        ``p.force`` and the damping part of ``p.torque`` from the last force pass (views;
        the next drift books their work: a caller that carries forces over writes them)."""
        return self._fe, self._fd, self._td

    def wall_resultants(self) -> np.ndarray:
        """(nw, 9) resultants of the particles on each wall at the last force pass [N]:
        total, conservative normal and damping part (a view; the next step books the walls'
        work from them)."""
        return self._wf

    def history_replaced(self) -> None:
        """Call after writing the contact history (``nl.hist/slip/etan`` and the wall
        ones) from outside: the stored elastic energy takes the new springs' energy (its
        normal part depends on the positions only)."""
        normal = self._elastic - self._spring
        self._spring = float(self.nl.etan.sum() + self.nl.wetan.sum())
        self._elastic = normal + self._spring

    def _ghost_index(self):
        """Rows whose contact work is booked as the ghosts' (a subclass may leave some out)."""
        return np.flatnonzero(self.p.kind == GHOST)


    def _check_cell_overlaps(self, allow: bool):
        b = self._branches()
        ov = self.p.radius[self.nl.pi] + self.p.radius[self.nl.pj] - np.linalg.norm(b, axis=1)
        if not allow and len(ov) and ov.max() > 0:
            k = int(np.argmax(ov))
            raise OverlapError(f"{int((ov > 0).sum())} overlapping particle pairs at the start "
                               f"(through the periodic faces too); the largest overlap is "
                               f"{ov[k]:.6g} m between particles "
                               f"{(int(self.nl.pi[k]), int(self.nl.pj[k]))} (pass "
                               f"allow_overlap=True to accept)")

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
        p, led = self.p, self._led
        ke, ok = _kinetic_finite(p.x, p.v, p.omega, p.mass, p.inertia, p.kind)
        if ok:
            budget = (self._e0 + abs(led["gravity"]) + abs(led["walls"]) + abs(led["ghosts"])
                      + abs(led["cell"]) + abs(led["external"]))
            ok = ke <= self.blowup_factor * budget + 1e-300
        if not ok:
            why = "NaN in x, v or omega" if not np.isfinite(p.v).all() else "kinetic energy jump"
            if self._good is not None:
                np.savez(self.state_path, **self._good)
            raise BlowUpError(f"blow-up ({why}) at step {self.nsteps}, t = {self.time:.6g} s "
                              f"(dt = {self.dt:.4g} s); last good state written to "
                              f"{self.state_path}", self.state_path)
        self._check_domain()
        g = self._good
        if g is None or g["x"].shape != p.x.shape:
            self._good = dict(p.state_dict(), time=self.time, step=self.nsteps)
        else:  # into the same buffers (no fresh pages to fault in at every check)
            for k in _STATE_KEYS:
                np.copyto(g[k], getattr(p, k))
            g["dim"], g["time"], g["step"] = np.int64(p.dim), self.time, self.nsteps

    def contacts(self):
        """(i, j) (k,) int64 of touching particle pairs now."""
        nl, r = self.nl, self.p.radius
        t = np.linalg.norm(self._branches(), axis=1) < r[nl.pi] + r[nl.pj]
        return nl.pi[t], nl.pj[t]
