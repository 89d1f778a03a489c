"""Where the RVEs of `coupling.fe2` live, and how their per-point values travel.

Every quadrature point has a *home*, the rank owning its cell (its strain, stress and
tangent, the macro problem's side), and a *worker*, the rank holding its RVE. At first the
worker is the home. An RVE's cost changes as the body deforms (a point in a band, or near a
weak cell, relaxes for more DEM steps than one outside), and a Newton iteration waits for
the slowest rank, so after a load step :func:`balance` may move RVEs to even the ranks'
work of that step: the RVE's state travels (`dem.rve.RVE.state_dict`, the continuation is
bit for bit), the home stays. Every rank runs the same deterministic :func:`balance` on
the same gathered costs, so no rank has to announce the moves.

Costs are counted in particle-steps (the DEM steps an RVE ran, relaxations and tangents,
times its grains), not seconds: the placement, hence the run, is then the same from run to
run whatever else shares the cores.
"""

from __future__ import annotations

from mpi4py import MPI

import numpy as np

__all__ = ["Placement", "balance"]


def balance(cost: np.ndarray, worker: np.ndarray, size: int, tolerance: float) -> np.ndarray:
    """New worker of every point, moving few points: while the most loaded rank is more than
    ``tolerance`` x the mean load above the least loaded one, move from it to the least
    loaded the point whose cost is nearest half their gap (only points cheaper than the gap
    lower the larger of the two; ties: the lowest point). cost, worker: (points,) arrays in
    global point order, the same on every rank; returns a new array."""
    worker = np.array(worker, dtype=np.int64)
    cost = np.asarray(cost, float)
    load = np.bincount(worker, cost, minlength=size)
    mean = load.mean()
    for _ in range(len(cost)):  # each move lowers the top load: never more moves than points
        a, b = int(np.argmax(load)), int(np.argmin(load))
        gap = load[a] - load[b]
        if mean <= 0 or gap <= tolerance * mean:
            break
        mine = np.flatnonzero((worker == a) & (cost > 0) & (cost < gap))
        if len(mine) == 0:
            break
        i = int(mine[np.argmin(np.abs(cost[mine] - 0.5 * gap))])
        worker[i] = b
        load[a] -= cost[i]
        load[b] += cost[i]
    return worker


class Placement:
    """Homes and workers of the points of an FE2 run (see the module docstring).

    Args:
        comm: the mesh's communicator.
        home_points: global numbers of the points owned here (0 .. total - 1 over the ranks).
    """

    def __init__(self, comm: MPI.Comm, home_points: np.ndarray):
        self.comm = comm
        parts = comm.allgather(np.asarray(home_points, np.int64))
        total = sum(len(p) for p in parts)
        self.home = np.empty(total, np.int64)
        for r, p in enumerate(parts):
            self.home[p] = r
        if np.bincount(np.concatenate(parts), minlength=total).max(initial=1) != 1:
            raise ValueError("Placement: a point is owned by two ranks")
        self.worker = self.home.copy()

    def held(self) -> np.ndarray:
        """Global numbers of the points whose RVE this rank holds (ascending)."""
        return np.flatnonzero(self.worker == self.comm.rank)

    def to_workers(self, values: dict[int, object]) -> dict[int, object]:
        """``{point: value}`` given at the points' homes, received at their workers.
        Collective."""
        return self._route(values, self.worker)

    def to_homes(self, values: dict[int, object]) -> dict[int, object]:
        """``{point: value}`` given at the points' workers, received at their homes.
        Collective."""
        return self._route(values, self.home)

    def _route(self, values, dest):
        comm = self.comm
        if comm.size == 1:
            return dict(values)
        out = [{} for _ in range(comm.size)]
        for g, v in values.items():
            out[int(dest[g])][g] = v
        got = {}
        for part in comm.alltoall(out):
            got.update(part)
        return got

    def move(self, worker: np.ndarray, states: dict[int, object]) -> dict[int, object]:
        """Adopt ``worker`` (the same on every rank); ``states``: ``{point: state}`` of the
        points held here, from which those leaving are sent to their new workers. Returns the
        states of the points arriving here. Collective."""
        leaving = {g: s for g, s in states.items() if worker[g] != self.comm.rank}
        self.worker = np.array(worker, np.int64)
        return self._route(leaving, self.worker)
