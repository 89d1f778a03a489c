"""`DistributedSimulation`: a `dem.Simulation` split over the MPI ranks by space (the scheme:
`dem.parallel`); its set-up, stepping, external forces, state and collective checks."""

from __future__ import annotations

import hashlib
import os
import tempfile

import numpy as np

from dem.contact import ContactMaterial
from dem.errors import BlowUpError, DomainError, TimeStepError
from dem.integrate import Simulation
from dem.ledger import _kinetic_finite
from dem.parallel.bisection import RecursiveBisection, _cut_axes
from dem.parallel.decomposition import Decomposition
from dem.parallel.local_run import (
    GID,
    INER,
    KIND,
    MASS,
    MAT,
    NCOL,
    RAD,
    XAT,
    V,
    W,
    X,
    _history_rows,
    _LocalMotion,
    _LocalSimulation,
    _particle_rows,
)
from dem.parallel.ranks import _agree, _exchange_rows, _mpi
from dem.parallel.results import _SUMS, CollectiveResults
from dem.state import FREE, Particles
from dem.timestep import DEFAULT_SAFETY, choose_dt, critical_dt
from dem.walls import WallSet

__all__ = ["DistributedSimulation"]


def _differs_across_ranks(comm, sim):
    """None if the `Simulation` sim has the same state on every rank of comm (checksums of
    the entries of its `state_dict` and its external forces), else a ValueError naming the
    ranks and the entries that differ from rank 0's."""
    d = sim.state_dict()
    rows, f = sim.external_force()
    d.update({"external.rows": rows, "external.force": f,
              "prescribed_pairs": sim.prescribed_pairs})
    sums = {k: hashlib.sha256(np.ascontiguousarray(d[k]).tobytes()).hexdigest()[:16]
            for k in sorted(d)}
    every = comm.allgather(sums)
    bad = [r for r, c in enumerate(every) if c != every[0]]
    if not bad:
        return None
    keys = sorted({k for r in bad for k in every[0].keys() | every[r].keys()
                   if every[0].get(k) != every[r].get(k)})
    return ValueError(f"from_simulation: the serial state differs across the ranks (checksum "
                      f"of sim.state_dict() entries: ranks {bad} differ from rank 0 in "
                      f"{keys[:8]}{' ...' if len(keys) > 8 else ''}); build or load the same "
                      f"Simulation, to the bit, on every rank")


class DistributedSimulation(Decomposition, CollectiveResults):
    """A `dem.Simulation` split over the ranks of ``comm`` by space, with halo exchange.

    Args:
        particles: the global `Particles` on rank 0 (ignored, may be None, elsewhere);
            global id = row. materials, walls, gravity, dt, safety, force_dt, v_max,
            domain, allow_overlap, blowup_factor, check_every, state_path: as
            `dem.Simulation` (dt is chosen on rank 0 from all particles, so it is the
            global minimum; set wall velocities through ``walls`` on every rank alike).
        comm: mpi4py communicator (default COMM_WORLD).
        owner: ``owner(x) -> ranks``: positions (n, 3) [m] -> ints in [0, comm.size),
            called collectively on each rank's owned particles at every decomposition
            (None: `RecursiveBisection` of the initial positions, its cuts along gravity).
        skin: Verlet skin of the local neighbour lists [m] (default 0.2 r_max, as
            `Simulation`). halo_skin: the decomposition's skin [m] (default 4 x skin: a
            decomposition costs a few neighbour builds, so it pays to have fewer for a
            wider halo; settle scene, 50k grains on 2 ranks: 4 x skin 5 % faster than
            2 x skin, 6 decompositions instead of 11): halo width 2 r_max + halo_skin; a
            new decomposition when a particle would move more than halo_skin / 2 since
            the last one (one rank: never, there is no halo).
        prescribed_pairs: as `dem.Simulation` (False: contacts of two particles that are not
            FREE are skipped, judged on the particles' own kinds, a halo copy's included).

    `from_simulation` continues a serial `dem.Simulation` held on every rank instead.

    As `dem.Simulation`: ``step(n, prescribed=..., decay=...)`` (motions by global id),
    `damping_removed`, `set_external_force` (by global id), `energy`, and `dem.relax` and
    `dem.unbalanced_force_ratio`, `dem.control.mean_force_ratio` take it (collectively),
    and ``step(hook=...)`` (collective: `dem.relax` with `dem.ServoWall` controllers; the
    walls' forces summed over the ranks by `wall_forces`). By global id: `values_of`
    (x, v, omega, force, torque of particles from their owners), `force_on` and
    `torque_on` (a clump's resultant). Set dt through the constructor (the local runs
    keep the one they were built with).

    Attributes: ``local`` (this rank's `Simulation`, None if it holds no particle),
    ``owned`` (bool mask of its owned particles), ``gid`` (their global ids), ``time``,
    ``nsteps``, ``dt``, ``decompositions`` (also those that found owners and halos
    unchanged), ``migrated`` (particles that changed rank, over all decompositions and
    ranks), ``walls`` (the `WallSet` of the local run, the same on every rank but for
    ``force``: this rank's share; set ``velocity`` alike on every rank).
    """

    def __init__(self, particles, materials, walls=(), gravity=(0.0, 0.0, 0.0), dt=None, *,
                 comm=None, owner=None, safety=None, force_dt=False, v_max=None, skin=None,
                 halo_skin=None, domain=None, allow_overlap=False, blowup_factor=10.0,
                 check_every=100, state_path=None, prescribed_pairs=True):
        self._configure(comm, materials, WallSet(walls), gravity, domain, blowup_factor,
                        check_every, state_path, prescribed_pairs)
        chunk = self._set_up_on_root(particles, dt, safety, force_dt, v_max, skin, halo_skin,
                                     allow_overlap, owner)
        self._start(owner, chunk)

    @classmethod
    def from_simulation(cls, sim, comm=None, *, owner=None, skin=None, halo_skin=None,
                        prescribed_pairs=None, blowup_factor=None, check_every=None,
                        state_path=None) -> DistributedSimulation:
        """The run that continues the serial `dem.Simulation` ``sim``, split over the ranks
        of ``comm`` (collective).

        ``sim`` must be on every rank with the same state to the bit (built the same way,
        or restored by ``sim.load_state``; a checksum of its `Simulation.state_dict` and
        external forces is compared across the ranks, ValueError naming the ranks that
        differ). Global id = the serial row. Carried over: the particle rows with the
        forces, force parts and positions at the last force pass, the contact history of
        every pair and wall contact (to the new owners of both particles), the walls'
        state and resultants, time, nsteps, dt, materials, gravity, domain box, the
        external forces (`set_external_force` by global id) and ``prescribed_pairs``; the
        energy ledger continues the serial one (its sums so far, ``initial`` and
        ``damping_removed`` are booked on rank 0: `energy` then equals what ``sim.energy()``
        would give after the same steps, to round-off; before the first step its
        ``elastic`` is that of the positions now, the serial run's of its last force pass:
        they differ if rows were moved from outside since, e.g. a penetrator lowered).
        ``sim`` is left untouched.

        owner, skin (default: the serial run's Verlet skin), halo_skin: as the constructor;
        prescribed_pairs, blowup_factor, check_every: default the serial run's; state_path:
        as the constructor. On one rank the run continues the serial one bit for bit.
        """
        comm = _mpi().COMM_WORLD if comm is None else comm
        err = None
        if not isinstance(sim, Simulation) or isinstance(sim, _LocalSimulation):
            err = ValueError(f"from_simulation: sim must be a dem.Simulation, got "
                             f"{type(sim).__name__}")
        elif sim.cell is not None:
            err = ValueError("from_simulation: a run in a periodic cell cannot be distributed")
        _agree(comm, err)
        _agree(comm, _differs_across_ranks(comm, sim))
        self = cls.__new__(cls)
        walls = WallSet(sim.walls.specs)
        walls.load_state(sim.walls.state_dict())
        self._configure(comm, sim.materials, walls, sim.gravity, sim.domain,
                        sim.blowup_factor if blowup_factor is None else blowup_factor,
                        sim.check_every if check_every is None else check_every, state_path,
                        sim.prescribed_pairs if prescribed_pairs is None else prescribed_pairs)
        chunk = self._set_up_from(sim, skin, halo_skin, owner)
        self._start(owner, chunk, sim)
        return self

    def _configure(self, comm, materials, walls, gravity, domain, blowup_factor, check_every,
                   state_path, prescribed_pairs):
        self.comm = _mpi().COMM_WORLD if comm is None else comm
        mats = [materials] if isinstance(materials, ContactMaterial) else list(materials)
        self.materials = mats
        self.walls = walls
        self.gravity = np.asarray(gravity, float).reshape(3)
        self.domain = None if domain is None else np.asarray(domain, float).reshape(2, 3)
        self.blowup_factor, self.check_every = float(blowup_factor), int(check_every)
        self.prescribed_pairs = bool(prescribed_pairs)
        self.state_path = state_path or os.path.join(tempfile.gettempdir(),
                                                  f"dem_last_good_state_{os.getpid()}.npz")

    def _start(self, owner, chunk, serial=None):
        """Counters, ledger and the first decomposition of this rank's rows ``chunk``
        (``serial``: the `Simulation` they come from, on every rank)."""
        self.owner = owner if owner is not None else self._bisection
        self.time, self.nsteps, self.decompositions, self.migrated = 0.0, 0, 0, 0
        #: wall time [s] in the halo exchanges (a wait for the slowest rank included) and
        #: in the decompositions, since the start (not checkpointed)
        self.timings = {"exchange": 0.0, "decompose": 0.0}
        # this rank's share of the ledger sums over the local runs before the present one,
        # and the spring energy of the present run's pairs another rank books, at its start
        self._bank = dict.fromkeys(_SUMS, 0.0)
        self._damped = 0.0  # its share of `damping_removed` likewise
        self._unbooked0 = 0.0
        self._pk = self._decay = None  # a step call's prescribed motions and damping
        self._hook, self._stop = None, False  # a step call's hook, and its request to stop
        self._force_sums = None  # a step call's force sums (gids, out)
        self._wall_total = None  # `wall_forces` of the last force pass, once summed
        self.local, self._plan = None, None
        self._ext = None   # (global ids (k,) sorted, forces (k, 3) [N]) of set_external_force
        if serial is not None:
            rows, f = serial.external_force()
            if len(rows):
                order = np.argsort(rows)
                self._ext = (np.asarray(rows, np.int64)[order], np.asarray(f, float)[order])
        self._decompose(chunk, serial)
        if serial is None:
            t = self._totals()
            self._e0 = t["kinetic_translational"] + t["kinetic_rotational"] + t["elastic"]
            self._shadow0 = t["shadow"]
        else:  # the serial ledger goes on: its sums so far on rank 0
            led = serial.ledger()
            self._e0, self._shadow0 = led["initial"], led["initial_shadow"]
            self.time, self.nsteps = float(serial.time), int(serial.nsteps)
            if self.comm.rank == 0:
                for k in _SUMS:
                    self._bank[k] += led[k]
                self._damped += float(serial.damping_removed)
        self._good = None
        self._check()

    # ---------------------------------------------------------------- set-up
    def _set_up_on_root(self, particles, dt, safety, force_dt, v_max, skin, halo_skin,
                        allow_overlap, owner):
        """Checks and the time step on rank 0, the particles scattered in id blocks."""
        comm, err, info, blocks = self.comm, None, None, None
        if comm.rank == 0:
            try:
                p = particles
                if not isinstance(p, Particles):
                    raise ValueError("particles must be a dem.Particles on rank 0")
                if p.material.max(initial=0) >= len(self.materials):
                    raise ValueError(f"particles.material refers to material "
                                     f"{p.material.max()} but only {len(self.materials)} given")
                if len(self.walls) and self.walls.material.max() >= len(self.materials):
                    # (checked here: a rank whose local run would find it alone would hang)
                    raise ValueError("a PlaneWall.material index is beyond the material list")
                safety = DEFAULT_SAFETY[self.materials[0].law] if safety is None else safety
                dt = choose_dt(dt, critical_dt(p, self.materials, v_max), safety, force_dt)
                rmax = float(p.radius.max())
                if not allow_overlap:  # as `Simulation`: round-off contacts are not overlaps
                    p.check_overlaps(tol=1e-9 * rmax)
                skin = 0.2 * rmax if skin is None else float(skin)
                halo_skin = 4.0 * skin if halo_skin is None else float(halo_skin)
                if not (skin >= 0 and halo_skin > 0):
                    raise ValueError(f"skin must be >= 0 m and halo_skin > 0 m, got "
                                     f"{skin!r}, {halo_skin!r}")
                rows = np.zeros((p.n, NCOL))
                rows[:, GID] = np.arange(p.n)
                rows[:, X], rows[:, V], rows[:, W] = p.x, p.v, p.omega
                rows[:, RAD], rows[:, MASS], rows[:, INER] = p.radius, p.mass, p.inertia
                rows[:, MAT], rows[:, KIND] = p.material, p.kind
                rows[:, XAT] = p.x
                blocks = np.array_split(rows, comm.size)
                rcb = None if owner is not None else RecursiveBisection.from_points(
                    p.x, comm.size, _cut_axes(self.gravity))
                info = (dt, rmax, skin, halo_skin, p.n, p.dim, rcb, p.kind.copy())
            except Exception as e:  # raised on every rank, not only here
                err = e
        _agree(comm, err)
        # kinds: every particle's kind by global id (a prescribed motion is checked on it)
        (self.dt, self.rmax, self.skin, self.halo_skin, self.ngid, self.dim,
         self._bisection, self._kinds) = comm.bcast(info, root=0)
        return comm.scatter(blocks, root=0)

    def _set_up_from(self, sim, skin, halo_skin, owner):
        """`_set_up_on_root` for a serial run on every rank: its dt; this rank's id block of
        its rows."""
        comm, p, err = self.comm, sim.p, None
        skin = sim.nl.skin if skin is None else float(skin)
        halo_skin = 4.0 * skin if halo_skin is None else float(halo_skin)
        if p.n == 0:
            err = "from_simulation: sim has no particles"
        elif not (skin >= 0 and halo_skin > 0):
            err = f"skin must be >= 0 m and halo_skin > 0 m, got {skin!r}, {halo_skin!r}"
        _agree(comm, err)
        self.dt, self.rmax, self.skin, self.halo_skin = float(sim.dt), float(p.radius.max()), \
            skin, halo_skin
        self.ngid, self.dim, self._kinds = p.n, p.dim, p.kind.copy()
        self._bisection = None if owner is not None else RecursiveBisection.from_points(
            p.x, comm.size, _cut_axes(self.gravity))
        idx = np.array_split(np.arange(p.n), comm.size)[comm.rank]
        return _particle_rows(sim, idx, idx)

    def _serial_history(self, sim, rows, new):
        """The contact history of the serial run ``sim`` at the new owners of both
        particles (collective): each rank sends the pairs whose lower id, and the wall
        contacts whose particle, is in its block ``rows`` (new owners ``new``)."""
        comm, nl = self.comm, sim.nl
        owner_of = np.concatenate(comm.allgather(new)) if comm.size > 1 else new  # by id
        mine = np.zeros(self.ngid, bool)
        mine[rows[:, GID].astype(np.int64)] = True
        (kp, pairs), (kw, wall) = _history_rows(nl, mine, np.arange(self.ngid))
        d1, d2 = owner_of[nl.pi[kp]], owner_of[nl.pj[kp]]
        two = d2 != d1  # both new owners of the pair need its history
        pairs, pdest = np.vstack([pairs, pairs[two]]), np.r_[d1, d2[two]]
        return (_exchange_rows(comm, pairs, pdest),
                _exchange_rows(comm, wall, owner_of[nl.wi[kw]]))

    # ---------------------------------------------------------------- stepping
    def step(self, n: int = 1, hook=None, prescribed=None, decay: float | None = None,
             sums=None) -> int:
        """Advance n steps of dt on every rank (collective, the same arguments on every
        rank); returns n.

        ``prescribed``, ``decay``: as `Simulation.step`, with the motions' rows naming
        GHOST particles by global id: every rank writes them into the copies it holds
        (owned and halo) before each step's drift, the same bits as the serial run at
        every step of the call, through decompositions; ``decay`` scales the owned FREE
        particles' v and omega before each step's drift, the energy it takes out booked as
        dissipated and summed in `damping_removed`. ``hook()``: as `Simulation.step`'s, run
        after each step's force pass, before its second half-kick, on every rank: it is
        collective (it may call `wall_forces`, and set wall velocities, alike on every
        rank; ``time`` and ``nsteps`` hold their values at the start of the call), and a
        true return, the same on every rank, ends the call after that step. ``sums``: a
        pair (gids (k,) int, out (k, 3) float): after every force pass the forces of the
        particles ``gids`` that this rank owns are added to their rows of ``out`` by the
        local run's own loop (`Simulation.step`'s sums; a hook would cost a Python call a
        step); rows of particles owned elsewhere are left as they are (the caller sums
        ``out`` over the ranks). Returns the number of steps done."""
        n = int(n)
        if sums is not None and np.shape(sums[1]) != (np.size(sums[0]), 3):
            raise ValueError(f"sums: out must have shape ({np.size(sums[0])}, 3), got {np.shape(sums[1])}")
        self._force_sums = None if sums is None else (np.asarray(sums[0], np.int64).ravel(), sums[1])
        self._pk = None if prescribed is None else prescribed.pack(n, self.dt, self._kinds)
        self._decay, self._hook, self._stop = decay, hook, False
        at = 0  # steps done in this call (the prescribed coefficients' row)
        while at < n and not self._stop:
            k = min(n - at, self.check_every - self.nsteps % self.check_every)
            while k > 0 and not self._stop:
                done = self._advance(k, at)
                k, at = k - done, at + done
            if self.nsteps % self.check_every == 0:
                self._check()
        if self.nsteps % self.check_every:
            self._check()
        self._pk = self._decay = self._hook = self._force_sums = None
        return at

    def _local_sums(self):
        """The call's ``sums`` for the local run now: (positions in gids, (local rows, a
        zeroed buffer)), or None."""
        if self._force_sums is None or self.local is None:
            return None
        at, rows = self.owned_rows(self._force_sums[0])
        return at, (rows, np.zeros((len(rows), 3)))

    def _local_motion(self, at: int) -> _LocalMotion | None:
        """The call's prescribed motions (packed by global id) of the rows this rank holds,
        from step ``at`` of the call on (None: none here)."""
        pk, s = self._pk, self.local
        if pk is None or s is None or len(self.gid) == 0:
            return None
        rows = pk[0]
        loc = np.minimum(np.searchsorted(self.gid, rows), len(self.gid) - 1)  # gid: sorted
        here = self.gid[loc] == rows
        if not here.any():
            return None
        arrays = (loc[here],) + tuple(np.ascontiguousarray(a[here]) for a in pk[1:8])
        return _LocalMotion(arrays, pk[8], at)

    def _advance(self, n: int, at: int = 0) -> int:
        """Up to n steps in one call of the local run (one rank: all n; else until the
        halo would go stale, then a decomposition), from step ``at`` of the `step` call;
        returns the steps done."""
        decay = self._decay
        self._wall_total = None
        if self.comm.size == 1:  # no halo, nothing to exchange or decompose
            summed = self._local_sums()
            done = self.local.step(n, hook=None if self._hook is None else self._after_pass,
                                   prescribed=self._local_motion(at), decay=decay,
                                   sums=None if summed is None else summed[1])
        else:
            motion = self._local_motion(at)
            if motion is not None:
                # the prescribed particles where the coming drift will see them: the
                # displacement criterion and a decomposition see a jump of the motion too
                motion.write(self.local.p)
            if self._exchange(1):
                self._decompose()
                if self._exchange(1):
                    raise TimeStepError(f"a particle moves more than halo_skin/2 = "
                                        f"{0.5 * self.halo_skin:.4g} m in one step (dt = "
                                        f"{self.dt:.4g} s): raise halo_skin or lower dt")
                motion = self._local_motion(at)  # of the new local run
            self._left = n
            summed = self._local_sums()
            local_sums = None if summed is None else summed[1]
            if self.local is not None and self._hook is None and decay is None:
                # nothing to run after a force pass: the exchange between the steps, and the
                # local run keeps its fused loop (one numba call a step, not the Python loop)
                done = self.local.step(n, prescribed=motion, sums=local_sums, pause_every=1,
                                       pause=self._between_fused_steps)
                self._wall_total = None   # (the last exchange's sum is of the force pass before)
            elif self.local is not None:
                done = self.local.step(n, hook=self._between_steps, prescribed=motion,
                                       decay=decay, sums=local_sums)
            else:
                done = n
                for k in range(n):
                    self.walls.advance(self.dt)
                    if self._between_steps():
                        done = k + 1
                        break
        if summed is not None:
            self._force_sums[1][summed[0]] += summed[1][1]
        for _ in range(done):
            self.time += self.dt
        self.nsteps += done
        return done

    def _between_steps(self) -> bool:
        """`Simulation.step` hook, after each force pass (collective): True to end the
        local call after this step (the next drift could carry a particle beyond the halo);
        else the halo copies as the next step's drift will make them. The last step of a
        call does neither: the next call decides and refreshes from the state it ends in.
        The caller's hook runs then, at every force pass (the exchange has summed the
        walls' forces; after the last step `wall_forces` sums them)."""
        self._wall_total = None
        self._left -= 1
        last = self._left == 0
        stale = not last and self._exchange(2)
        stop = self._call_hook()
        if last or stale or stop:
            return stale or stop
        if not self._relisted and self._d2 > (0.5 * self.skin) ** 2:
            # the local lists would soon rebuild, rank by rank: all of them now instead
            # (once between decompositions: then the displacements from the lists' build
            # are no longer those from the halos')
            self._rebuild_lists()
            self._relisted = True
        return False

    def _between_fused_steps(self) -> bool:
        """`Simulation.step` pause between two steps of a local call without a caller's hook
        or damping (collective): True to end the local call there (the coming drift could
        carry a particle beyond the halo); else the halo copies as the coming half-kick and
        drift will make them, and the lists rebuilt on every rank once the skin is half
        spent (as `_between_steps`, which runs before the step's second half-kick)."""
        self._wall_total = None
        if self._exchange(1):
            return True
        if not self._relisted and self._d2 > (0.5 * self.skin) ** 2:
            self._rebuild_lists()
            self._relisted = True
        return False

    def _after_pass(self) -> bool:
        """One rank's `Simulation.step` hook: the walls' forces are new; the caller's hook."""
        self._wall_total = None
        return self._call_hook()

    def _call_hook(self) -> bool:
        """The caller's hook, if any (collective; True: it ends the `step` call after this
        step)."""
        if self._hook is None:
            return False
        self._stop = bool(self._hook())
        return self._stop

    # ---------------------------------------------------------------- external forces
    def set_external_force(self, gids, force) -> None:
        """Collective (the same arguments on every rank): `Simulation.set_external_force`
        by global id. The constant force ``force`` [N] ((k, 3), or (3,) for every one) acts
        on the FREE particles ``gids`` (k,) from the next force pass on, on whichever rank
        owns each (it follows a particle that migrates); its work is ``work_external`` in
        `energy`. ``gids=None`` removes it."""
        err = None
        if gids is None:
            new = None
        else:
            gids = np.asarray(gids, np.int64).ravel()
            f = np.broadcast_to(np.asarray(force, float), (len(gids), 3)).copy()
            if len(gids) and (gids.min() < 0 or gids.max() >= self.ngid):
                err = ValueError(f"set_external_force: gids must lie in [0, {self.ngid}), got "
                                 f"{gids.min()}..{gids.max()}")
            elif len(np.unique(gids)) != len(gids):
                err = ValueError("set_external_force: gids repeat")
            elif not np.isfinite(f).all():
                err = ValueError("set_external_force: force is not finite")
            elif self.dim == 2 and (f[:, 2] != 0).any():
                err = ValueError("set_external_force: force[:, 2] must be 0 for 2D disks")
            elif self.local is not None:
                mine = self.owned & np.isin(self.gid, gids)
                if (self.local.p.kind[mine] != FREE).any():
                    err = ValueError("set_external_force: gids must be FREE particles (the "
                                     "others' motion is prescribed)")
            order = np.argsort(gids)
            new = (gids[order], f[order])
        _agree(self.comm, err)
        self._ext = new
        self._install_external(included=False)

    def _install_external(self, included: bool) -> None:
        """Hand the local run its owned share of the external forces (``included``: its
        force arrays, carried from the last local run or a state, hold them already)."""
        s = self.local
        if s is None:
            return
        if self._ext is None:
            s.set_external_force(None, None)
            return
        gids, f = self._ext
        rows = np.flatnonzero(self.owned & np.isin(self.gid, gids))
        mine = f[np.searchsorted(gids, self.gid[rows])]
        carried = s.p.force[rows].copy() if included else None
        s.set_external_force(rows, mine)
        if included:  # the carried bits (taking the force out and back in would round)
            s.p.force[rows] = carried

    # ---------------------------------------------------------------- state (collective)
    def state_dict(self) -> dict:
        """This rank's part of the run's state, flat and ``np.savez``-ready (one file per
        rank): its local run's `Simulation.state_dict` (``local.*``, absent on a rank that
        holds no particle), the global ids and owned mask of its rows, the halo exchange's
        plan (``plan.*``), the positions the halos were made at, the ledger's banked sums
        (``bank.*``), the walls, time and counters. `load_state` restores it into a
        DistributedSimulation constructed the same way on as many ranks; the run then
        continues as this one would, bit for bit."""
        send, recv, _, _, scount, rcount = self._plan
        d = dict(ranks=int(self.comm.size), rank=int(self.comm.rank), ngid=int(self.ngid),
                 time=float(self.time), nsteps=int(self.nsteps), dt=float(self.dt),
                 decompositions=int(self.decompositions), migrated=int(self.migrated),
                 initial=float(self._e0), initial_shadow=float(self._shadow0),
                 unbooked0=float(self._unbooked0), relisted=bool(self._relisted),
                 damping_removed=self._damping_share(),
                 gid=self.gid.copy(), owned=self.owned.copy(), xref=self._xref.copy(),
                 has_local=self.local is not None)
        d.update({"plan.send": send.copy(), "plan.recv": recv.copy(),
                  "plan.scount": scount.copy(), "plan.rcount": rcount.copy(),
                  "plan.send_dest": self._send_dest.copy()})
        d.update({f"bank.{k}": float(v) for k, v in self._bank.items()})
        d.update({f"walls.{k}": v for k, v in self.walls.state_dict().items()})
        if self.local is not None:
            d.update({f"local.{k}": v for k, v in self.local.state_dict().items()})
        return d

    def load_state(self, d) -> None:
        """Restore this rank's `state_dict` (collective). Raises ValueError on every rank,
        naming the key, if a rank's state does not fit (another rank count, particle count
        or configuration)."""
        d, err = dict(d), None
        try:
            for key, have in (("ranks", self.comm.size), ("rank", self.comm.rank),
                              ("ngid", self.ngid)):
                if key not in d:
                    raise ValueError(f"state has no {key!r}")
                if int(d[key]) != have:
                    raise ValueError(f"state {key!r} is {int(d[key])}, this run has {have}")
            if bool(d["has_local"]):
                q = {k[16:]: v for k, v in d.items() if k.startswith("local.particles.")}
                p = Particles(q["x"], q["v"], q["omega"], q["radius"], q["mass"], q["inertia"],
                              q["material"], q["kind"], self.dim)
                halo = ~np.asarray(d["owned"], bool)
                if halo.shape != (p.n,):
                    raise ValueError(f"state 'owned' has shape {halo.shape}, 'local.particles.x'"
                                     f" {p.n} rows")
                try:
                    self._local_run(p, halo, np.asarray(d["gid"], np.int64)).load_state(
                        {k[6:]: v for k, v in d.items() if k.startswith("local.")})
                except ValueError as e:
                    raise ValueError(f"local run: {e}") from None
            else:
                self.local = None
                self.walls.load_state({k[6:]: v for k, v in d.items() if k.startswith("walls.")})
        except (KeyError, ValueError) as e:
            err = e if isinstance(e, ValueError) else ValueError(f"state has no {e.args[0]!r}")
        except IndexError:
            err = ValueError(f"state 'gid' holds ids beyond this run's {self.ngid}")
        _agree(self.comm, err)
        self.gid, self.owned = np.array(d["gid"], np.int64), np.array(d["owned"], bool)
        self._xref = np.array(d["xref"], float).reshape(-1, 3)
        self._send_dest = np.array(d["plan.send_dest"], np.int64)
        self._set_plan(np.array(d["plan.send"], np.int64), np.array(d["plan.recv"], np.int64),
                       np.array(d["plan.scount"], np.int64), np.array(d["plan.rcount"], np.int64),
                       len(self.gid))
        self.time, self.nsteps, self.dt = float(d["time"]), int(d["nsteps"]), float(d["dt"])
        self.decompositions, self.migrated = int(d["decompositions"]), int(d["migrated"])
        self._e0, self._shadow0 = float(d["initial"]), float(d["initial_shadow"])
        self._unbooked0, self._relisted = float(d["unbooked0"]), bool(d["relisted"])
        # bank.external: absent from states written before external forces were distributed
        self._bank = {k: float(d.get(f"bank.{k}", 0.0)) for k in _SUMS}
        # (the local run restored starts its own count from 0)
        self._damped = float(d.get("damping_removed", 0.0))
        self._install_external(included=True)
        self._good = None
        self._wall_total = None
        self._check()

    # ---------------------------------------------------------------- checks
    def _check_domain(self):
        err = None
        if self.domain is not None and self.local is not None:
            p, (lo, hi) = self.local.p, self.domain
            out = self.owned & (p.kind == FREE) & ((p.x < lo) | (p.x > hi)).any(axis=1)
            if out.any():
                i = int(np.flatnonzero(out)[0])
                err = DomainError(f"particle {self.gid[i]} left the domain box {lo.tolist()}"
                                  f"..{hi.tolist()} at x = {p.x[i].tolist()} (t = "
                                  f"{self.time:.6g} s, step {self.nsteps})")
        _agree(self.comm, err)

    def _check(self):
        """Collective blow-up check (NaN, or kinetic energy above blowup_factor x the energy
        put in); on failure rank 0 writes the last good state, gathered."""
        s, sums = self.local, self._sums()
        ke, finite = (0.0, True) if s is None else _kinetic_finite(
            s.p.x, s.p.v, s.p.omega, s.p.mass, s.p.inertia, s.p.kind)
        v = np.array([ke, float(not finite)] + [sums[k] for k in _SUMS[2:]])  # the works
        if self.comm.size > 1:
            v = self.comm.allreduce(v)
        ke, finite = v[0], v[1] == 0.0
        ok = finite and ke <= self.blowup_factor * (self._e0 + np.abs(v[2:]).sum()) + 1e-300
        if not ok:
            why = "NaN in x, v or omega" if not finite else "kinetic energy jump"
            good = self.comm.gather(self._good, root=0)
            if self.comm.rank == 0 and all(g is not None for g in good):
                st = np.vstack(good)
                st = st[np.argsort(st[:, GID])]
                np.savez(self.state_path, gid=st[:, GID], x=st[:, X], v=st[:, V],
                         omega=st[:, W], time=self._good_at[0], step=self._good_at[1])
            raise BlowUpError(f"blow-up ({why}) at step {self.nsteps}, t = {self.time:.6g} s "
                              f"(dt = {self.dt:.4g} s); last good state written to "
                              f"{self.state_path}", self.state_path)
        self._check_domain()
        self._good = np.empty((0, 10)) if s is None else np.column_stack(
            [self.gid, s.p.x, s.p.v, s.p.omega])[self.owned]  # columns GID, X, V, W
        self._good_at = (self.time, self.nsteps)
