"""The decomposition of a `DistributedSimulation` over the ranks: new owners, migration with
the contact history, halos, the local run built from them; and the halo exchange of every
step (the owners' coming state predicted into their copies, one ``Alltoallv``)."""

from __future__ import annotations

import time

import numpy as np
from numba import njit

from dem.contact import HIST
from dem.neighbours import carry_history
from dem.parallel.local_run import (
    FD,
    FE,
    GID,
    HCOL,
    INER,
    KIND,
    MASS,
    MAT,
    NCOL,
    RAD,
    TD,
    XAT,
    F,
    T,
    V,
    W,
    X,
    _history_rows,
    _LocalSimulation,
    _particle_rows,
)
from dem.parallel.ranks import _agree, _exchange_rows, _in_rank_order, _mpi, _rank_sum, _spec
from dem.state import FREE, GHOST, Particles
from dem.walls import PlaneWall

__all__ = ["Decomposition"]


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


def _head_rows(nwalls: int) -> int:
    """Header rows (9 columns) opening each halo message: the sender's largest coming
    displacement (column 0 of every one), then its share of the walls' forces (3 a wall)
    in columns 1-8."""
    return max(1, -(-3 * nwalls // 8))


class Decomposition:
    """The decomposition and halo exchange of `dem.parallel.DistributedSimulation` (a base of
    it: the plan, owners and local run they keep are its attributes)."""

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
        """`_decompose_now`, its wall time added to ``timings["decompose"]``."""
        t0 = time.perf_counter()
        self._decompose_now(chunk, serial)
        self.timings["decompose"] += time.perf_counter() - t0

    def _decompose_now(self, chunk=None, serial=None):
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
        """`_exchange_now`, its wall time (waiting for the other ranks included) added to
        ``timings["exchange"]``."""
        t0 = time.perf_counter()
        stale = self._exchange_now(kicks)
        self.timings["exchange"] += time.perf_counter() - t0
        return stale

    def _exchange_now(self, kicks: int) -> bool:
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
