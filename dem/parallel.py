"""MPI spatial domain decomposition of a DEM run: one `Simulation` per rank, halos of ghosts.

Each rank owns the particles of its subdomain (recursive bisection of the particle box along
its longest axis not along gravity, or any ``owner(x) -> ranks`` the caller passes, e.g. the
FE partition) and holds, as GHOST particles of its local `dem.Simulation`, copies of the
other ranks' particles within ``2 r_max + halo_skin`` of its owned particles' box. The n
steps of a call run in one call of the local `Simulation.step` (its fused kick + drift
pass, no per-step Python set-up); its hook, after each force pass, has the owners send x,
v, omega of the copies *as the coming half-kicks and drift will make them* (one
``Alltoallv`` of a contiguous buffer, whose header rows also carry each rank's largest
coming displacement, so it is the step's only synchronisation); a GHOST keeps its
prescribed state through the step, so the local run's force pass sees the same neighbours
as the serial one. A pair of an owned particle and a copy is computed on both ranks from
identical data, each rank integrating its own copy of the pair's tangential history. On
one rank nothing is exchanged: the run is the local `Simulation`.

Why the result equals the serial run to round-off (in practice bit for bit): the local arrays
are kept in global-id order, so local pairs (i < j) sort as the serial ones; every contact of
an owned particle is in the local list; the pair loop sums onto particles in pair order. An
owned particle so sees the same contacts, in the same order, with the same data.

Ownership is fixed between *decompositions*; one happens when some particle would move more
than ``halo_skin / 2`` since the last one (so no pair outside the halo can have closed). A
decomposition migrates particles to their new owners with the forces of the last step and
their contact history, keyed by global ids: a pair's history is authoritative on the owner
of its lower-id particle, which sends it to both new owners.

Prescribed GHOST motions (``step(prescribed=...)``, rows by global id) are packed once per
call and written by every rank into the copies it holds, owned and halo, with the
coefficients of the call's step (a call split into local calls writes the serial bits); the
first step's state is written before the halo exchange, so that a jump of the motion is seen
by the displacement criterion and a decomposition. ``decay`` damps the owned FREE particles
in the local run, and the halo prediction applies it where the integrator does.

Walls are the same on every rank (each local run carries a copy and advances it with the
wall's velocity); a rank's wall force is its owned particles' share. `wall_forces` sums
the shares in rank order (the same bits on every rank and every run), and a ``hook`` of
`step` runs on every rank after each force pass, as `Simulation.step`'s: a `dem.ServoWall`
there reads the summed force and sets the same velocity on every rank (`dem.relax` with
controllers). The sum differs from the serial run's by round-off (another order).

The energy ledger (`DistributedSimulation.energy`) books every term once: a particle's
kinetic energy and works on its owner, a pair's elastic energy and the change of its
spring energy on the owner of its lower id, a wall contact on the particle's owner (a halo
copy has no wall contacts, nor contacts with other copies: the local lists drop them).

`DistributedSimulation.from_simulation` continues a serial `dem.Simulation` held, the same
to the bit, on every rank (e.g. a coupled run's DE window consolidated serially, then pushed
over the ranks): the first decomposition takes each rank's id block of its rows, with their
forces and the contact history of the block's pairs and wall contacts, routed to the new
owners of both particles as a migration routes it; the walls, time, external forces and the
ledger's sums so far come along.

mpi4py is imported lazily (``import dem`` stays free of MPI); every public method of
`DistributedSimulation` is collective.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from dataclasses import dataclass

import numpy as np
from numba import njit

from dem.contact import HIST, ContactMaterial
from dem.control import mean_force_sums, unbalanced_force_sums
from dem.errors import BlowUpError, DomainError, TimeStepError
from dem.forces import NOUT, pair_forces
from dem.integrate import Simulation
from dem.ledger import _kinetic_finite
from dem.neighbours import carry_history
from dem.prescribed import _prescribe
from dem.state import FREE, GHOST, Particles
from dem.timestep import DEFAULT_SAFETY, choose_dt, critical_dt
from dem.walls import PlaneWall, WallSet

__all__ = ["DistributedSimulation", "RecursiveBisection"]

# particle rows exchanged at a decomposition: global id, state, the forces of the last step
# (the next half-kick needs them) with their conservative and damping parts (the next drift
# books their half of the step's work), and where the last force pass saw the particle (XAT:
# a prescribed GHOST may have been moved on since, and the ledger books its work over the
# displacement from there)
GID, X, V, W, RAD, MASS, INER, MAT, KIND = 0, slice(1, 4), slice(4, 7), slice(7, 10), 10, 11, \
    12, 13, 14
F, T, FE, FD, TD = slice(15, 18), slice(18, 21), slice(21, 24), slice(24, 27), slice(27, 30)
XAT = slice(30, 33)
NCOL = 33
# contact history rows: global ids (pair: i < j; wall: particle, wall), history (HIST: spring
# and the dashpot's history, `dem.contact`), slip, energy
HCOL = 4 + HIST
# the ledger's sums over steps (`Simulation._led` keys)
_SUMS = ("dissipated", "friction", "gravity", "walls", "ghosts", "cell", "external")


# ---------------------------------------------------------------- ownership
@dataclass(frozen=True, eq=False)
class RecursiveBisection:
    """Recursive coordinate bisection: node k splits along ``axis[k]`` at ``cut[k]`` [m];
    ``below[k]``/``above[k]`` are child nodes (>= 0) or leaves ``-1 - rank``. Call it on
    positions (n, 3) to get owner ranks (n,) int64 (a point on a cut goes above)."""

    axis: np.ndarray
    cut: np.ndarray
    below: np.ndarray
    above: np.ndarray
    nranks: int

    @classmethod
    def from_points(cls, x, nranks: int, axes=(0, 1, 2)) -> RecursiveBisection:
        """Cuts giving each of ``nranks`` ranks (about) as many of the points x (n, 3) [m],
        each cut normal to the longest of ``axes`` of the box of the points it splits."""
        if not (isinstance(nranks, int | np.integer) and nranks >= 1):
            raise ValueError(f"nranks must be an int >= 1, got {nranks!r}")
        allowed = np.zeros(3, bool)
        allowed[list(axes)] = True
        x = np.asarray(x, float).reshape(-1, 3)
        nodes = []  # (axis, cut, below, above)

        def split(pts, r0, r1):
            if r1 - r0 == 1:
                return -1 - r0
            k = len(nodes)
            nodes.append(None)
            span = pts.max(axis=0) - pts.min(axis=0) if len(pts) else np.zeros(3)
            ax = int(np.argmax(np.where(allowed, span, -1.0)))
            rm = (r0 + r1) // 2
            c = np.sort(pts[:, ax])
            m = int(round(len(c) * (rm - r0) / (r1 - r0)))
            if len(c) == 0:
                cut = 0.0
            elif m <= 0:
                cut = c[0]
            elif m >= len(c):
                cut = np.nextafter(c[-1], np.inf)
            else:
                cut = 0.5 * (c[m - 1] + c[m])
            lo = pts[:, ax] < cut
            nodes[k] = (ax, float(cut), split(pts[lo], r0, rm), split(pts[~lo], rm, r1))
            return k

        split(x, 0, int(nranks))
        a = np.array(nodes, dtype=object).reshape(-1, 4)
        return cls(a[:, 0].astype(np.int64), a[:, 1].astype(float), a[:, 2].astype(np.int64),
                   a[:, 3].astype(np.int64), int(nranks))

    def __call__(self, x) -> np.ndarray:
        x = np.asarray(x, float).reshape(-1, 3)
        node = np.zeros(x.shape[0], np.int64) if len(self.axis) else np.full(x.shape[0], -1)
        live = node >= 0
        while live.any():
            k = node[live]
            up = x[live, self.axis[k]] >= self.cut[k]
            node[live] = np.where(up, self.above[k], self.below[k])
            live = node >= 0
        return -1 - node


def _cut_axes(gravity):
    """Axes the default bisection may cut normal to: under gravity not its own axis. Grains
    fall and pile up along g, so a cut across g sees them migrate through it and leaves the
    contacts (most of the work) on the rank below; cuts along g stay balanced."""
    g = np.abs(np.asarray(gravity, float))
    return (0, 1, 2) if not g.any() else tuple(a for a in range(3) if a != int(np.argmax(g)))


# ---------------------------------------------------------------- kernels
@njit(cache=True)
def _predict(x, v, omega, force, torque, mass, inertia, kind, owned, slot, g, h, dt, kicks,
             decay, xref, buf):
    """One pass over the local rows after ``kicks`` half-kicks (h [s]) with the forces now
    and a drift (dt [s]) (1 between two steps, 2 from a step's force pass: its second
    half-kick, then the next step's first), v and omega scaled by ``decay`` before the
    last half-kick (`Simulation.step` damps before a step's drift; 1.0: no damping, and
    x 1.0 changes no bit). Returns the largest squared distance [m^2] of an owned particle
    from xref then (a criterion: rounding aside; not FREE: after dt v, the prescribed
    motion) and writes rows [x, v, omega] (9,) of the particles with slot >= 0 to
    buf[slot] as `Simulation.step` will make them (FREE: the same operations in the same
    order, so the same bits; the others as prescribed now)."""
    d2 = 0.0
    hk = kicks * h
    hl = hk - h  # the half-kicks before the damping
    for i in range(x.shape[0]):
        if kind[i] == 0 and decay == 1.0:  # FREE: owned (halo copies are GHOST)
            a = hk / mass[i]
            b0 = x[i, 0] + dt * (v[i, 0] + a * force[i, 0] + hk * g[0]) - xref[i, 0]
            b1 = x[i, 1] + dt * (v[i, 1] + a * force[i, 1] + hk * g[1]) - xref[i, 1]
            b2 = x[i, 2] + dt * (v[i, 2] + a * force[i, 2] + hk * g[2]) - xref[i, 2]
        elif kind[i] == 0:
            a, b = hl / mass[i], h / mass[i]
            b0 = x[i, 0] + dt * (decay * (v[i, 0] + a * force[i, 0] + hl * g[0])
                                 + b * force[i, 0] + h * g[0]) - xref[i, 0]
            b1 = x[i, 1] + dt * (decay * (v[i, 1] + a * force[i, 1] + hl * g[1])
                                 + b * force[i, 1] + h * g[1]) - xref[i, 1]
            b2 = x[i, 2] + dt * (decay * (v[i, 2] + a * force[i, 2] + hl * g[2])
                                 + b * force[i, 2] + h * g[2]) - xref[i, 2]
        elif owned[i]:
            b0 = x[i, 0] + dt * v[i, 0] - xref[i, 0]
            b1 = x[i, 1] + dt * v[i, 1] - xref[i, 1]
            b2 = x[i, 2] + dt * v[i, 2] - xref[i, 2]
        else:
            continue
        d2 = max(d2, b0 * b0 + b1 * b1 + b2 * b2)
        k = slot[i]
        if k < 0:
            continue
        for c in range(3):
            if kind[i] == 0:
                u = v[i, c]
                w = omega[i, c]
                for q in range(kicks):
                    if q == kicks - 1:
                        u *= decay
                        w *= decay
                    u += h * (force[i, c] / mass[i] + g[c])
                    w += h * torque[i, c] / inertia[i]
                buf[k, c] = x[i, c] + dt * u
                buf[k, 3 + c] = u
                buf[k, 6 + c] = w
            else:
                buf[k, c], buf[k, 3 + c], buf[k, 6 + c] = x[i, c], v[i, c], omega[i, c]
    return d2


@njit(cache=True)
def _unpack(idx, buf, x, v, omega):
    for k in range(idx.shape[0]):
        i = idx[k]
        if i < 0:  # a header
            continue
        for c in range(3):
            x[i, c] = buf[k, c]
            v[i, c] = buf[k, 3 + c]
            omega[i, c] = buf[k, 6 + c]


# ---------------------------------------------------------------- communication
_MPI = None


def _mpi():
    """mpi4py.MPI, imported on first use (``import dem`` stays free of MPI)."""
    global _MPI
    if _MPI is None:
        from mpi4py import MPI

        _MPI = MPI
    return _MPI


def _spec(buf, rows_per_rank):
    """mpi4py buffer spec [buf, (counts, displacements), DOUBLE] for rows of buf."""
    c = np.asarray(rows_per_rank, np.int64) * (buf.shape[1] if buf.ndim > 1 else 1)
    return [buf, (c, np.concatenate([[0], np.cumsum(c)[:-1]])), _mpi().DOUBLE]


def _exchange_rows(comm, rows, dest):
    """Send row k of rows (n, K) float64 to rank dest[k]; returns the rows received (m, K),
    ordered by source rank, then by the sender's order."""
    order = np.argsort(dest, kind="stable")
    send = np.ascontiguousarray(rows[order])
    scount = np.bincount(dest, minlength=comm.size).astype(np.int64)
    rcount = np.empty_like(scount)
    comm.Alltoall(scount, rcount)
    recv = np.empty((int(rcount.sum()), rows.shape[1]))
    comm.Alltoallv(_spec(send, scount), _spec(recv, rcount))
    return recv


def _in_rank_order(parts) -> np.ndarray:
    """parts[0] + parts[1] + ... (one part a rank, in rank order)."""
    total = parts[0].copy()
    for r in range(1, len(parts)):
        total += parts[r]
    return total


def _rank_sum(comm, a) -> np.ndarray:
    """The sum of the float array ``a`` over the ranks, added in rank order: the same bits on
    every rank and every run (an Allreduce leaves the order to the MPI library)."""
    a = np.ascontiguousarray(a, float)
    if comm.size == 1:
        return a.copy()
    parts = np.empty((comm.size,) + a.shape)
    comm.Allgather(a, parts)
    return _in_rank_order(parts)


def _head_rows(nwalls: int) -> int:
    """Header rows (9 columns) opening each halo message: the sender's largest coming
    displacement (column 0 of every one), then its share of the walls' forces (3 a wall)
    in columns 1-8."""
    return max(1, -(-3 * nwalls // 8))


def _agree(comm, error):
    """Raise on every rank the error (an exception or a message) of the first rank that has
    one, so that no rank is left waiting in a collective call."""
    bad = [e for e in comm.allgather(error) if e is not None]
    if bad:
        raise bad[0] if isinstance(bad[0], Exception) else ValueError(bad[0])


# ---------------------------------------------------------------- the local run
class _LocalSimulation(Simulation):
    """`Simulation` of one rank's owned particles plus halo copies (GHOST; ``halo`` (n,)
    bool marks them). Its own blow-up and domain checks are off: an error on one rank alone
    would leave the others waiting in a collective call, so `DistributedSimulation` checks
    collectively.

    A halo copy is only there to act on owned particles: its contacts with other copies
    and with the walls are dropped from the lists (their forces were never used, and its
    wall contacts would book the owner's wall work twice), and its work is not booked as
    the work of a ghost (the owner books the particle's work)."""

    def __init__(self, particles, halo, kinds, *args, **kwargs):
        self.halo, self.kinds = halo, kinds  # kinds: the particles' own (n,)
        super().__init__(particles, *args, check_every=1 << 62, **kwargs)

    def _ghost_index(self):
        return np.flatnonzero((self.p.kind == GHOST) & ~self.halo)

    def _check(self):
        pass

    def positions_at_last_pass(self) -> np.ndarray:
        """(n, 3) [m]: where the last force pass saw each row (the ledger's ghost positions
        for the owned GHOSTs, which a prescribed motion may have moved since; x for the
        rest)."""
        return _positions_at_last_pass(self)

    def set_positions_at_last_pass(self, x) -> None:
        """The inverse of `positions_at_last_pass` for a run built from carried rows: its
        constructor took the ghosts' positions now (the next step books their work from the
        last force pass, as the serial run does)."""
        if len(self._ghosts):
            self._at = (x[self._ghosts].copy(), self._at[1])

    def _own_kinds(self) -> np.ndarray:
        # a halo copy of a FREE particle is GHOST here: the pairs are judged on its own kind
        return self.kinds

    def _prune(self, nl):
        nl.keep_pairs(~(self.halo[nl.pi] & self.halo[nl.pj]))
        nl.keep_walls(~self.halo[nl.wi])
        super()._prune(nl)


def _positions_at_last_pass(s) -> np.ndarray:
    """(n, 3) [m]: where the last force pass of the `Simulation` s saw each row (its
    ledger's positions of the GHOST rows it books, which a prescribed motion may have
    moved since; x for the rest)."""
    x = s.p.x.copy()
    if len(s._ghosts):
        x[s._ghosts] = s._at[0]
    return x


def _particle_rows(s, idx, gid) -> np.ndarray:
    """Rows (k, NCOL) of the rows ``idx`` (k,) of the `Simulation` s, global ids ``gid``."""
    p = s.p
    rows = np.empty((len(idx), NCOL))
    rows[:, GID] = gid
    rows[:, X], rows[:, V], rows[:, W] = p.x[idx], p.v[idx], p.omega[idx]
    rows[:, RAD], rows[:, MASS], rows[:, INER] = p.radius[idx], p.mass[idx], p.inertia[idx]
    rows[:, MAT], rows[:, KIND] = p.material[idx], p.kind[idx]
    rows[:, F], rows[:, T] = p.force[idx], p.torque[idx]
    rows[:, XAT] = _positions_at_last_pass(s)[idx]
    fe, fd, td = s.force_parts()
    rows[:, FE], rows[:, FD], rows[:, TD] = fe[idx], fd[idx], td[idx]
    return rows


def _history_rows(nl, mine, gid):
    """The non-zero contact history of the neighbour list nl whose (first) particle is
    ``mine`` (bool by row): (pairs' indices (k,), rows (k, HCOL)) and the same of the
    wall contacts; rows keyed by global ids (``gid`` by row; pair: lower id first)."""

    def entries(i, j, hist, slip, etan):
        k = np.flatnonzero(mine[i] & ((hist != 0).any(axis=1) | (slip != 0) | (etan != 0)))
        return k, np.column_stack([gid[i[k]], j[k], hist[k], slip[k], etan[k]])

    return (entries(nl.pi, gid[nl.pj], nl.hist, nl.slip, nl.etan),
            entries(nl.wi, nl.ww, nl.whist, nl.wslip, nl.wetan))


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


class _LocalMotion:
    """The rows of one local run in a `Prescribed` packed by global id, from step ``start``
    of the distributed `step` call on: what `Simulation.step` takes as ``prescribed`` (it
    calls ``pack``). A call split into several local calls so writes the same bits at
    every step as one serial call (the coefficients of step s are taken, not recomputed
    for a shorter call)."""

    def __init__(self, arrays, coef, start):
        self.arrays, self.coef, self.start = arrays, coef, start

    def pack(self, n, dt, kind):  # (the rows were checked on the global kinds)
        return (*self.arrays, self.coef[self.start:self.start + n])

    def write(self, p) -> None:
        """The state of the first step into p's rows (before that step's drift, as the
        local call will write it)."""
        _prescribe(0, *self.pack(1, 0.0, None), p.x, p.v, p.omega)


# ---------------------------------------------------------------- the distributed run
class DistributedSimulation:
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
        # this rank's share of the ledger sums over the local runs before the present one,
        # and the spring energy of the present run's pairs another rank books, at its start
        self._bank = dict.fromkeys(_SUMS, 0.0)
        self._damped = 0.0  # its share of `damping_removed` likewise
        self._unbooked0 = 0.0
        self._pk = self._decay = None  # a step call's prescribed motions and damping
        self._hook, self._stop = None, False  # a step call's hook, and its request to stop
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

    # ---------------------------------------------------------------- decomposition
    def _owned_rows(self):
        """Rows of the owned particles, and the authoritative contact history: non-zero
        entries of the pairs whose lower id is owned and of owned particles' wall contacts,
        with the pairs' local indices (k) for routing."""
        oi = np.flatnonzero(self.owned)
        pairs, wall = _history_rows(self.local.nl, self.owned, self.gid)
        return oi, _particle_rows(self.local, oi, self.gid[oi]), pairs, wall

    def _new_owners(self, x):
        ranks = np.asarray(self.owner(x))
        err = None  # a message, raised as ValueError on every rank
        if ranks.shape != (x.shape[0],) or not np.issubdtype(ranks.dtype, np.integer) or (
                len(ranks) and (ranks.min() < 0 or ranks.max() >= self.comm.size)):
            err = (f"owner(x) must return ints in [0, {self.comm.size}) of shape "
                   f"({x.shape[0]},); got dtype {ranks.dtype}, shape {ranks.shape}")
        _agree(self.comm, err)
        return ranks.astype(np.int64)

    def _decompose(self, chunk=None, serial=None):
        """Collective: new owners, migration with history, halos, a new local run (``chunk``:
        the first, of this rank's rows; ``serial``: the `Simulation` they continue, with
        its forces, history and wall resultants)."""
        comm, me = self.comm, self.comm.rank
        empty = np.empty((0, HCOL))
        wf = None
        if chunk is not None:
            rows, pairs, wall = chunk, empty, empty
            new = self._new_owners(rows[:, X])
            if serial is not None:
                pairs, wall = self._serial_history(serial, rows, new)
                wf = serial.wall_resultants().copy()
        else:
            self._check_domain()
            if self._unchanged():  # the same owners and halos: the local run goes on
                if self.local is not None:
                    self._xref = self.local.p.x.copy()
                self._rebuild_lists()
                self._relisted = False
                self.decompositions += 1
                return
            s = self.local
            self._bank = self._sums()  # the ledger of this local run: banked
            self._damped = self._damping_share()
            wf = self._wall_share()
            if s is not None:
                oi, rows, (kp, pairs), (kw, wall) = self._owned_rows()
            else:
                oi, rows, kp, kw = np.empty(0, np.int64), np.empty((0, NCOL)), [], []
                pairs = wall = empty
            new = self._new_owners(rows[:, X])
            # the new owner of every halo copy, from its present owner
            owner_of = np.full(0 if s is None else s.p.n, -1, np.int64)
            owner_of[oi] = new
            owner_of = self._forward(owner_of)
            if s is not None:
                d1, d2 = owner_of[s.nl.pi[kp]], owner_of[s.nl.pj[kp]]
                two = d2 != d1  # both new owners of the pair need its history
                pairs, pdest = np.vstack([pairs, pairs[two]]), np.r_[d1, d2[two]]
                wdest = owner_of[s.nl.wi[kw]]
            else:
                pdest = wdest = np.empty(0, np.int64)
            pairs = _exchange_rows(comm, pairs, pdest)
            wall = _exchange_rows(comm, wall, wdest)
            self.migrated += int(comm.allreduce(int((new != me).sum())))
        own = _exchange_rows(comm, rows, new)
        halo = self._halo_rows(own)
        self._build_local(own, halo, pairs, wall, carried=wf is not None)
        if wf is not None:
            has = me if self.local is not None else comm.size
            first = comm.allreduce(has, op=_mpi().MIN) if comm.size > 1 else has
            if self.local is not None:
                self.local.wall_resultants()[:] = wf if me == first else 0.0
                self.walls.force[:] = self.local.wall_resultants()[:, :3]  # the share
        self._unbooked0 = self._unbooked_spring()
        self._relisted = False  # the new local run built its lists now
        self.decompositions += 1

    def _rebuild_lists(self):
        """The local neighbour list built now, as on every other rank (were each rank to
        rebuild when its own skin runs out, the others would wait for it in turn)."""
        if self.local is not None:
            self.local.rebuild_neighbours()

    def _wall_share(self):
        """The wall resultants (nw, 9) of the last force pass (sum of the ranks' shares):
        the next runs' trapezoidal wall work starts from them, all on the lowest rank that
        holds particles (any split adds up to the same resultants)."""
        nw = len(self.walls)
        wf = np.zeros((nw, 9)) if self.local is None else self.local.wall_resultants().copy()
        return _rank_sum(self.comm, wf) if nw else wf

    def _halo_sends(self, x):
        """Collective: which of the owned positions x (n, 3) go as halo copies to which rank
        (those in the rank's owned box inflated by the halo width): rows (k,) of x and
        their destinations (k,), by destination."""
        comm = self.comm
        box = np.array([x.min(axis=0), x.max(axis=0)]) if len(x) else \
            np.array([np.full(3, np.inf), np.full(3, -np.inf)])
        boxes = np.array(comm.allgather(box))
        reach = (2.0 * self.rmax + self.halo_skin) * (1.0 + 1e-9)
        idx, dest = [np.empty(0, np.int64)], [np.empty(0, np.int64)]
        for r in range(comm.size):
            if r != comm.rank:
                k = np.flatnonzero(((x >= boxes[r, 0] - reach) & (x <= boxes[r, 1] + reach))
                                   .all(axis=1))
                idx.append(k)
                dest.append(np.full(len(k), r, np.int64))
        return np.concatenate(idx), np.concatenate(dest)

    def _halo_rows(self, own):
        """Copies of this rank's particles to the ranks that need them (`_halo_sends`);
        returns the copies received, in plan order."""
        self._send_own, self._send_dest = self._halo_sends(own[:, X])
        return _exchange_rows(self.comm, own[self._send_own], self._send_dest)

    def _unchanged(self) -> bool:
        """Collective: would a decomposition now keep every particle on its rank and every
        halo as it is? (Then it need not build a new local run: the grains of a settling
        bed mostly fall along the cuts.)"""
        s, me = self.local, self.comm.rank
        oi = np.flatnonzero(self.owned) if s is not None else np.empty(0, np.int64)
        x = s.p.x[oi] if s is not None else np.empty((0, 3))
        same = bool((self._new_owners(x) == me).all())
        k, dest = self._halo_sends(x)
        send = self._plan[0]
        old = send[send >= 0]
        # the plan sends by destination, each block in the order of the rows; compare sets
        same &= len(old) == len(k) and all(
            np.array_equal(np.sort(old[self._send_dest == r]), oi[k[dest == r]])
            for r in range(self.comm.size) if r != me)
        return bool(self.comm.allreduce(int(same), op=_mpi().MIN)) if self.comm.size > 1 \
            else same

    def _build_local(self, own, halo, pairs, wall, carried):
        """The local `Simulation` of owned + halo rows in global-id order, the halo plan,
        and (``carried``: after t = 0) the forces and contact history brought along."""
        comm = self.comm
        rows = np.vstack([own, halo])
        is_halo = np.r_[np.zeros(len(own), bool), np.ones(len(halo), bool)]
        order = np.argsort(rows[:, GID], kind="stable")
        rows, is_halo = rows[order], is_halo[order]
        where = np.empty(len(rows), np.int64)
        where[order] = np.arange(len(rows))  # local index of row k of [own; halo]
        scount = np.bincount(self._send_dest, minlength=comm.size).astype(np.int64)
        rcount = np.empty_like(scount)
        comm.Alltoall(scount, rcount)
        # each message to another rank opens with header rows (index -1, `_head_rows`): the
        # sender's largest coming displacement, so one Alltoallv a step also decides
        # collectively whether to decompose, and its share of the walls' forces, so that
        # a servo after the step's force pass needs no other collective call
        others = np.arange(comm.size) != comm.rank
        heads = _head_rows(len(self.walls))

        def with_heads(idx, count):
            at = np.r_[0, np.cumsum(count)[:-1]][others]
            return np.insert(idx, np.repeat(at, heads), -1), count + heads * others

        send, scount = with_heads(where[self._send_own], scount)
        recv, rcount = with_heads(where[len(own):], rcount)
        self._set_plan(send, recv, scount, rcount, len(rows))
        self.gid, self.owned = rows[:, GID].astype(np.int64), ~is_halo
        self._xref = rows[:, X].copy()
        if len(rows) == 0:
            self.local = None
            return
        kind = rows[:, KIND].astype(np.int8)
        kind[is_halo & (kind == FREE)] = GHOST
        p = Particles(rows[:, X], rows[:, V], rows[:, W], rows[:, RAD], rows[:, MASS],
                      rows[:, INER], rows[:, MAT].astype(np.int32), kind, self.dim)
        sim = self._local_run(p, is_halo, self.gid)
        if carried:  # the constructor's force pass started from no history: replace it
            p.force[:], p.torque[:] = rows[:, F], rows[:, T]
            fe, fd, td = sim.force_parts()
            fe[:], fd[:], td[:] = rows[:, FE], rows[:, FD], rows[:, TD]
            self._install_history(sim.nl, pairs, wall)
            sim.history_replaced()
            sim.set_positions_at_last_pass(rows[:, XAT])
        self._install_external(included=carried)

    def _local_run(self, p, is_halo, gid):
        """A `_LocalSimulation` of p (halo copies ``is_halo``, global ids ``gid``) with the
        walls as they are, installed as ``self.local``."""
        w = self.walls
        specs = [PlaneWall(tuple(w.point[k]), tuple(w.normal[k]), tuple(w.velocity[k]),
                           int(w.material[k]), bool(w.rigid[k]), bool(w.free_only[k]))
                 for k in range(len(w))]
        sim = _LocalSimulation(p, is_halo, self._kinds[gid], self.materials, specs,
                               self.gravity, self.dt, force_dt=True, skin=self.skin,
                               allow_overlap=True, prescribed_pairs=self.prescribed_pairs)
        # the local run continues the walls exactly (a spec re-normalises the normal)
        for a in ("point", "normal", "velocity", "force"):
            getattr(sim.walls, a)[:] = getattr(w, a)
        self.walls, self.local = sim.walls, sim
        return sim

    def _set_plan(self, send, recv, scount, rcount, n):
        """The halo exchange's plan: local rows sent (send) and received into (recv), by
        rank (-1: a header row), rows per rank (scount, rcount), n local rows."""
        self._plan = (send, recv, _spec(np.zeros((len(send), 9)), scount),
                      _spec(np.empty((len(recv), 9)), rcount), scount, rcount)
        self._heads, self._sheads = np.flatnonzero(recv < 0), np.flatnonzero(send < 0)
        # (from the plan: a state written with fewer header rows sends no wall shares)
        self._nhead = len(self._heads) // max(self.comm.size - 1, 1)
        # the buffer row each local row sent is predicted into, and the rows of a particle
        # sent to more than one rank: copies of its first (dst, src)
        sent = np.flatnonzero(send >= 0)
        local, first = np.unique(send[sent], return_index=True)
        self._slot = np.full(n, -1, np.int64)
        self._slot[local] = sent[first]
        src = self._slot[send[sent]]
        self._dups = (sent[src != sent], src[src != sent])

    def _install_history(self, nl, pairs, wall):
        """Contact history rows keyed by global ids into the neighbour list (pairs not
        received start from zero: they are new, or of two halo copies)."""
        g, n, nw = self.gid, self.ngid, max(len(self.walls), 1)
        for rows, key, names, m in (
                (pairs, g[nl.pi] * n + g[nl.pj], ("hist", "slip", "etan"), n),
                (wall, g[nl.wi] * nw + nl.ww, ("whist", "wslip", "wetan"), nw)):
            keys = rows[:, 0].astype(np.int64) * m + rows[:, 1].astype(np.int64)
            keys, first = np.unique(keys, return_index=True)  # a pair sent twice: same data
            r = rows[first]
            new = carry_history(keys, key, np.ascontiguousarray(r[:, 2:2 + HIST]),
                                r[:, 2 + HIST].astype(np.int8), r[:, 3 + HIST].copy())
            for name, a in zip(names, new, strict=True):
                setattr(nl, name, a)

    # ---------------------------------------------------------------- halo exchange
    def _exchange(self, kicks: int) -> bool:
        """Collective, once per step: True if the drift after ``kicks`` coming half-kicks
        could carry an owned particle more than halo_skin / 2 from where the halos were
        made (then decompose first); else the owners' x, v, omega after those half-kicks
        and the drift are now in their halo copies (GHOST: kept through the local step).
        Either way the walls' forces of the last force pass are summed (`wall_forces`)."""
        send, recv, sspec, rspec, _, _ = self._plan
        s, d2 = self.local, 0.0
        share = self._pack_wall_share(sspec[0])
        if s is not None:
            p = s.p
            d2 = _predict(p.x, p.v, p.omega, p.force, p.torque, p.mass, p.inertia, p.kind,
                          self.owned, self._slot, self.gravity, 0.5 * self.dt, self.dt, kicks,
                          1.0 if self._decay is None else float(self._decay), self._xref,
                          sspec[0])
            if len(self._dups[0]):
                sspec[0][self._dups[0]] = sspec[0][self._dups[1]]
        sspec[0][self._sheads, 0] = d2
        self.comm.Alltoallv(sspec, rspec)
        d2 = self._d2 = max(d2, rspec[0][self._heads, 0].max(initial=0.0))
        if share is not None:
            got = rspec[0][self._heads, 1:].reshape(self.comm.size - 1, -1)[:, :len(share)]
            parts = np.insert(got, self.comm.rank, share, axis=0)  # in rank order
            self._wall_total = _in_rank_order(parts).reshape(-1, 3)
        if d2 > (0.5 * self.halo_skin * (1.0 - 1e-9)) ** 2:  # (rounding of the estimate)
            return True
        if s is not None:
            _unpack(recv, rspec[0], s.p.x, s.p.v, s.p.omega)
        return False

    def _pack_wall_share(self, buf):
        """This rank's share of the walls' forces (3 nw,) into the header rows of the send
        buffer ``buf``; returns it (None: no walls, or no room in a restored plan)."""
        nw = len(self.walls)
        if nw == 0 or 8 * self._nhead < 3 * nw:
            return None
        share = np.zeros(3 * nw) if self.local is None else \
            self.local.wall_resultants()[:, :3].ravel()
        block = np.zeros(8 * self._nhead)
        block[:3 * nw] = share
        buf[self._sheads, 1:] = np.tile(block.reshape(self._nhead, 8), (self.comm.size - 1, 1))
        return share

    def _refresh_halos(self) -> None:
        """Collective, between step calls: the halo copies take their owners' state now.
        (A call leaves them half a kick behind: its last step sends nothing. The next call's
        first exchange overwrites them, so this changes nothing in the run.)"""
        if self.comm.size == 1:
            return
        send, recv, sspec, rspec, _, _ = self._plan
        s = self.local
        if s is not None:
            p = s.p
            _predict(p.x, p.v, p.omega, p.force, p.torque, p.mass, p.inertia, p.kind,
                     self.owned, self._slot, self.gravity, 0.5 * self.dt, 0.0, 0, 1.0,
                     self._xref, sspec[0])
            if len(self._dups[0]):
                sspec[0][self._dups[0]] = sspec[0][self._dups[1]]
        self.comm.Alltoallv(sspec, rspec)
        if s is not None:
            _unpack(recv, rspec[0], s.p.x, s.p.v, s.p.omega)

    def _forward(self, values):
        """Int values (n_local,) of owned particles copied into their halo copies."""
        send, recv, _, _, sc, rc = self._plan
        rbuf = np.empty(len(recv))
        sbuf = np.zeros(len(send))
        sbuf[send >= 0] = values[send[send >= 0]]  # (header rows: nothing; a rank may be empty)
        self.comm.Alltoallv(_spec(sbuf, sc), _spec(rbuf, rc))
        copy = recv >= 0
        values[recv[copy]] = rbuf[copy].astype(values.dtype)
        return values

    # ---------------------------------------------------------------- stepping
    def step(self, n: int = 1, hook=None, prescribed=None, decay: float | None = None) -> int:
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
        true return, the same on every rank, ends the call after that step. Returns the
        number of steps done."""
        n = int(n)
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
        self._pk = self._decay = self._hook = None
        return at

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
            done = self.local.step(n, hook=None if self._hook is None else self._after_pass,
                                   prescribed=self._local_motion(at), decay=decay)
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
            if self.local is not None:
                done = self.local.step(n, hook=self._between_steps, prescribed=motion,
                                       decay=decay)
            else:
                done = n
                for k in range(n):
                    self.walls.advance(self.dt)
                    if self._between_steps():
                        done = k + 1
                        break
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

    # ---------------------------------------------------------------- results (collective)
    def _damping_share(self) -> float:
        """This rank's kinetic energy taken out by ``step(decay=...)`` so far [J]."""
        return self._damped + (0.0 if self.local is None else self.local.damping_removed)

    @property
    def damping_removed(self) -> float:
        """Kinetic energy taken out by ``step(decay=...)`` so far, all ranks [J] (as
        `Simulation.damping_removed`; collective: read it on every rank)."""
        d = self._damping_share()
        return float(self.comm.allreduce(d)) if self.comm.size > 1 else d

    def unbalanced_force_sums(self) -> np.ndarray:
        """(sum |F + m g|, sum |C|) [N] over the owned FREE particles of all ranks
        (`dem.control.unbalanced_force_ratio`'s sums; C: contact part of F)."""
        v = np.zeros(2) if self.local is None else np.array(
            unbalanced_force_sums(self.local, self.owned))
        return self.comm.allreduce(v) if self.comm.size > 1 else v

    def mean_force_sums(self) -> tuple[float, int, float, int]:
        """`dem.control.mean_force_ratio`'s sums over all ranks (collective): each rank's
        owned FREE particles and the contacts whose first particle it owns, counted with
        the particles' own kinds (a halo copy is GHOST in its local run)."""
        self._refresh_halos()  # a pair across ranks sees its copy's state now
        v = np.zeros(4)
        if self.local is not None:
            v[:] = mean_force_sums(self.local, self.owned, self._kinds[self.gid])
        v = _rank_sum(self.comm, v)
        return float(v[0]), int(v[1]), float(v[2]), int(v[3])

    def wall_forces(self) -> np.ndarray:
        """(nw, 3) [N]: the resultant of the particles on each wall at the last force pass,
        the ranks' shares added in rank order (the same bits on every rank and every run;
        collective, summed once per force pass: a `ServoWall` and `dem.relax`'s check read
        it). A view: do not write it."""
        if self._wall_total is None:
            nw = len(self.walls)
            share = np.zeros((nw, 3)) if self.local is None else \
                self.local.wall_resultants()[:, :3]
            self._wall_total = _rank_sum(self.comm, share)
        return self._wall_total

    def values_of(self, gids, key: str = "force") -> np.ndarray:
        """(k, 3) ``key`` (x, v, omega, force, torque) of the particles ``gids`` (k,), in
        that order, from their owners (exact: the other ranks add zeros). E.g. the forces
        on a prescribed clump's spheres, or where its GHOSTs are."""
        gids = np.asarray(gids, np.int64).ravel()
        err = None
        if key not in ("x", "v", "omega", "force", "torque"):
            err = ValueError(f"values_of: key must be x, v, omega, force or torque, got {key!r}")
        elif len(gids) and (gids.min() < 0 or gids.max() >= self.ngid):
            err = ValueError(f"values_of: gids must lie in [0, {self.ngid}), got "
                             f"{gids.min()}..{gids.max()}")
        _agree(self.comm, err)
        out = np.zeros((len(gids), 3))
        at, rows = self.owned_rows(gids)
        if len(at):
            out[at] = getattr(self.local.p, key)[rows]
        return self.comm.allreduce(out) if self.comm.size > 1 else out

    def owned_rows(self, gids) -> tuple[np.ndarray, np.ndarray]:
        """Of the particles ``gids`` (k,), those this rank owns: their positions in ``gids``
        and their rows in ``local`` (not collective; valid until the next decomposition,
        which replaces ``gid``)."""
        gids = np.asarray(gids, np.int64).ravel()
        if self.local is None or len(self.gid) == 0:
            return np.empty(0, np.int64), np.empty(0, np.int64)
        loc = np.minimum(np.searchsorted(self.gid, gids), len(self.gid) - 1)  # gid: sorted
        mine = (self.gid[loc] == gids) & self.owned[loc]
        return np.flatnonzero(mine), loc[mine]

    def force_on(self, gids) -> np.ndarray:
        """(3,) [N]: the sum of the forces on the particles ``gids`` (a clump's resultant,
        its own spheres' contacts included), summed in the order of gids as the serial
        ``sim.p.force[gids].sum(axis=0)``."""
        return self.values_of(gids, "force").sum(axis=0)

    def torque_on(self, gids, about) -> np.ndarray:
        """(3,) [N m]: the moment about the point ``about`` (3,) [m] of the forces and
        torques on the particles ``gids`` (sum of t_i + (x_i - about) x f_i)."""
        x, f = self.values_of(gids, "x"), self.values_of(gids, "force")
        t = self.values_of(gids, "torque")
        return (t + np.cross(x - np.asarray(about, float), f)).sum(axis=0)

    def kinetic_energy(self) -> np.ndarray:
        """(translational, rotational) kinetic energy of all FREE particles [J]."""
        k = np.zeros(2) if self.local is None else self.local.kinetic_energy()
        return self.comm.allreduce(k)

    def _unbooked_spring(self) -> float:
        """Spring energy [J] of the local pairs whose lower id is a halo copy: their owner
        books them (a pair across two ranks is computed on both)."""
        if self.local is None:
            return 0.0
        nl = self.local.nl
        return float(nl.etan[~self.owned[nl.pi]].sum())

    def _unbooked_elastic(self) -> float:
        """Elastic energy [J] (normal + spring) of the pairs `_unbooked_spring` names, at the
        last force pass: the normal part evaluated again (it depends on the positions only)
        on copies of the history, the spring part as stored."""
        s = self.local
        nl = s.nl
        k = np.flatnonzero(~self.owned[nl.pi])
        if len(k) == 0:
            return 0.0
        p = s.p
        out = np.zeros((len(k), NOUT))
        acc = [np.zeros_like(p.force) for _ in range(5)]
        pair_forces(nl.pi[k], nl.pj[k], p.x, p.v, p.omega, p.radius, p.mass, p.material,
                    s.table, nl.hist[k], nl.slip[k], nl.etan[k], s.dt, out, *acc, rows=True)
        return float((out[:, 18] - out[:, 22]).sum() + nl.etan[k].sum())

    def _sums(self) -> dict:
        """This rank's share of the ledger's sums over the steps so far [J] (`_SUMS`):
        its local runs' ledgers, the dissipation corrected by the change of the spring
        energy another rank books (the local run booked it as its own)."""
        out, s = dict(self._bank), self.local
        if s is not None:
            c = self._unbooked_spring() - self._unbooked0
            led = s.ledger()
            for k in _SUMS:
                out[k] += led[k] + (c if k in ("dissipated", "friction") else 0.0)
        return out

    def _totals(self, elastic: bool = True) -> dict:
        """Collective: kinetic (translational, rotational), elastic (0 unless ``elastic``),
        shadow and `_SUMS`, summed over the ranks [J]."""
        s, sums = self.local, self._sums()
        kt = kr = el = sh = 0.0
        if s is not None:
            kt, kr = s.kinetic_energy()
            sh = s.shadow_energy()
            el = s.ledger()["elastic"] - self._unbooked_elastic() if elastic else 0.0
        v = np.array([kt, kr, el, sh] + [sums[k] for k in _SUMS])
        if self.comm.size > 1:
            v = self.comm.allreduce(v)
        keys = ("kinetic_translational", "kinetic_rotational", "elastic", "shadow") + _SUMS
        return dict(zip(keys, (float(a) for a in v), strict=True))

    def energy(self) -> dict:
        """The ledger of `Simulation.energy` (the same keys) of the whole run [J].

        Each rank books its owned particles' kinetic energy, shadow and works, its walls'
        share of the wall contacts (a halo copy has none) and the pairs whose lower id it
        owns (a pair across two ranks is computed on both). Agrees with the serial run to
        round-off (sums in another order)."""
        t = self._totals()
        stored = (t["kinetic_translational"] + t["kinetic_rotational"] - t["shadow"]
                  + t["elastic"] + t["dissipated"])
        work = t["gravity"] + t["walls"] + t["ghosts"] + t["cell"] + t["external"]
        return dict(kinetic_translational=t["kinetic_translational"],
                    kinetic_rotational=t["kinetic_rotational"], elastic=t["elastic"],
                    dissipated_damping=t["dissipated"] - t["friction"],
                    dissipated_friction=t["friction"], work_gravity=t["gravity"],
                    work_walls=t["walls"], work_ghosts=t["ghosts"], work_cell=t["cell"],
                    work_external=t["external"], shadow=t["shadow"], initial=self._e0,
                    balance=stored - work - (self._e0 - self._shadow0))

    def gather(self, root: int = 0) -> dict | None:
        """On ``root``: x, v, omega, force, torque (N, 3) in global-id order and ``rank``
        (N,) (the owner); None elsewhere."""
        s = self.local
        keys = ("x", "v", "omega", "force", "torque")
        if s is None:
            part = (np.empty(0, np.int64), {k: np.empty((0, 3)) for k in keys})
        else:
            oi = np.flatnonzero(self.owned)
            part = (self.gid[oi], {k: getattr(s.p, k)[oi] for k in keys})
        parts = self.comm.gather(part, root=root)
        if self.comm.rank != root:
            return None
        gid = np.concatenate([q[0] for q in parts])
        order = np.argsort(gid)
        out = {k: np.concatenate([q[1][k] for q in parts])[order] for k in keys}
        out["rank"] = np.concatenate([np.full(len(q[0]), r) for r, q in enumerate(parts)])[
            order]
        return out

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
