"""The collective read-outs of a `DistributedSimulation`: the energy ledger summed over the
ranks, forces and values by global id, the walls' forces, the relaxation measures' sums,
the particles gathered on one rank."""

from __future__ import annotations

import numpy as np

from dem.control import mean_force_sums, unbalanced_force_sums
from dem.forces import NOUT, pair_forces
from dem.parallel.ranks import _agree, _rank_sum

__all__ = ["CollectiveResults"]


# the ledger's sums over steps (`Simulation._led` keys)
_SUMS = ("dissipated", "friction", "gravity", "walls", "ghosts", "cell", "external")


class CollectiveResults:
    """The collective results of `dem.parallel.DistributedSimulation` (a base of it: the
    local run, owned mask and banked sums they read are its attributes)."""

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
