"""One rank's part of a `DistributedSimulation`: its local `Simulation` of owned particles and
halo copies, the rows particles and contact history travel in between ranks, and the
prescribed motions of the rows it holds."""

from __future__ import annotations

import numpy as np

from dem.contact import HIST
from dem.integrate import Simulation
from dem.prescribed import _prescribe
from dem.state import GHOST

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
