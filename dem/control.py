"""Quasi-static control of a DEM run: dynamic relaxation and servo-controlled walls.

- :func:`relax`: mass-proportional damping (seed 001 eq. 91: ``M qdd + c M qd = F``) applied
  as an exact exponential velocity decay ``v <- v exp(-c dt)`` of the FREE particles each
  step, until the unbalanced-force ratio ``|F + m g| / |F|`` falls below ``tol``. The energy
  taken out is booked as damping dissipation, so the ledger still closes.
- :class:`ServoWall`: moves a planar wall along its normal to hold a confining stress
  (a proportional controller with a speed limit), as in triaxial/oedometer DEM practice.

Each function takes a `dem.Simulation` or a `dem.DistributedSimulation` (then collectively:
the same calls on every rank; a wall's force is the sum of the ranks' shares, `wall_force`,
and the equilibrium measures sum over the ranks' owned particles).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dem.state import FREE

__all__ = ["ServoWall", "relax", "unbalanced_force_ratio", "mean_force_ratio", "advance",
           "wall_force"]


def wall_force(sim, wall: int) -> np.ndarray:
    """(3,) [N]: the resultant of the particles on wall ``wall`` at the last force pass
    (``walls.force[wall]`` of a `Simulation`; of a `DistributedSimulation`, collective, the
    sum of every rank's share, the same bits on every rank: `DistributedSimulation.
    wall_forces`)."""
    total = getattr(sim, "wall_forces", None)
    return sim.walls.force[wall] if total is None else total()[wall]


@dataclass
class ServoWall:
    """Hold ``target`` [Pa, compression positive] on wall ``wall`` of area ``area`` [m^2, or m
    per unit thickness in 2D]: wall speed ``gain (target - measured)`` along its normal,
    clipped to ``v_max`` [m/s]."""

    wall: int
    target: float
    area: float
    gain: float
    v_max: float

    def __post_init__(self):
        for name in ("area", "gain", "v_max"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"ServoWall.{name} must be > 0, got {v!r}")
        if not math.isfinite(self.target):
            raise ValueError(f"ServoWall.target must be finite, got {self.target!r}")

    def stress(self, sim) -> float:
        """Compressive normal stress the particles put on the wall [Pa] (collective on a
        `DistributedSimulation`: its wall's force summed over the ranks)."""
        return float(-(wall_force(sim, self.wall) @ sim.walls.normal[self.wall]) / self.area)

    def __call__(self, sim) -> None:
        """Set the wall's velocity from the stress now (on a `DistributedSimulation` every
        rank sets the same: its ranks see the same summed force)."""
        w = sim.walls
        if not 0 <= self.wall < len(w):
            raise ValueError(f"ServoWall.wall = {self.wall} but the simulation has {len(w)} walls")
        speed = float(np.clip(self.gain * (self.target - self.stress(sim)), -self.v_max, self.v_max))
        w.velocity[self.wall] = speed * w.normal[self.wall]


def unbalanced_force_sums(sim, rows=None) -> tuple[float, float]:
    """``(sum_i |F_i + m_i g|, sum_i |C_i|)`` [N] over the FREE particles of a `Simulation`
    (and of the bool mask ``rows`` (n,) if given: a rank's owned ones), F the force on a
    particle (contacts and `Simulation.set_external_force`), C its contact part."""
    p = sim.p
    f = p.kind == FREE
    if rows is not None:
        f &= rows
    net = p.force[f] + p.mass[f, None] * sim.gravity
    c = p.force.copy()
    ext, fext = sim.external_force()
    c[ext] -= fext
    return float(np.linalg.norm(net, axis=1).sum()), float(np.linalg.norm(c[f], axis=1).sum())


def unbalanced_force_ratio(sim) -> float:
    """``sum_i |F_i + m_i g| / sum_i |C_i|`` over FREE particles (0 in equilibrium), F the
    force on a particle (contacts and `Simulation.set_external_force`), C its contact part.
    Collective on a `dem.DistributedSimulation` (its sums over the ranks' owned particles)."""
    sums = getattr(sim, "unbalanced_force_sums", None)  # a DistributedSimulation's
    net, contact = sums() if sums is not None else unbalanced_force_sums(sim)
    if contact == 0.0:
        return math.inf
    return float(net / contact)


def advance(sim, n: int, controllers=()) -> None:
    """``n`` steps with the controllers applied before each step."""
    for _ in range(int(n)):
        for c in controllers:
            c(sim)
        sim.step(1)


def mean_force_sums(sim, rows=None, kinds=None) -> tuple[float, int, float, int]:
    """(sum |F_i + m_i g| [N] over the FREE particles, their count, sum |f_c| [N] over the
    contacts that touch a FREE particle, their count): `mean_force_ratio`'s sums, of a
    `Simulation`'s rows ``rows`` (bool (n,), a rank's owned ones: a contact counts on the
    owner of its first particle) with ``kinds`` (n,) the particles' own kinds if not
    ``p.kind`` (a rank's halo copies are GHOST in its local run). Pairs of two GHOST
    particles (a rigid clump's own contacts) are left out."""
    p = sim.p
    kinds = p.kind if kinds is None else kinds
    free = kinds == FREE
    mine = free if rows is None else free & rows
    net = np.linalg.norm(p.force[mine] + p.mass[mine, None] * sim.gravity, axis=1)
    if rows is None:
        pairs, f = sim.contact_forces()
    else:  # the kinds of the local run would drop a halo grain's contacts with a GHOST
        pairs, f = sim.contact_forces(skip_ghost_pairs=False)
    touching = free[pairs[:, 0]] | free[pairs[:, 1]]
    if rows is not None:
        touching &= rows[pairs[:, 0]]
    fc = np.linalg.norm(f[touching], axis=1)
    return float(net.sum()), int(net.size), float(fc.sum()), int(fc.size)


def mean_force_ratio(sim) -> float:
    """The mean unbalanced force over the FREE particles, ``|F_i + m_i g|``, over the mean
    contact force of their contacts (PFC's ratio): the measure of equilibrium for a packing
    loaded through walls, whose particles' contact resultants are all unbalanced force
    (`unbalanced_force_ratio` is then 1 until the very end). It evaluates the pair loop once
    more (`Simulation.contact_forces`); collective on a `DistributedSimulation` (its sums
    over the ranks)."""
    sums = getattr(sim, "mean_force_sums", None)  # a DistributedSimulation's
    net, n_net, contact, n_contact = sums() if sums is not None else mean_force_sums(sim)
    if n_contact == 0 or n_net == 0:
        return math.inf
    return float((net / n_net) / (contact / n_contact))


def relax(sim, tol: float = 1e-4, max_steps: int = 200_000, damping: float | None = None,
          controllers=(), check_every: int = 50, ratio=unbalanced_force_ratio) -> dict:
    """Dynamic relaxation to static equilibrium; returns steps, ratio and energy removed.

    ``ratio``: the measure of equilibrium, ``ratio(sim) < tol`` (`unbalanced_force_ratio`;
    `mean_force_ratio` for a packing loaded through walls).

    ``damping`` c [1/s] defaults to ``0.02 / dt`` (2 % of the velocity per step). Raises
    ``RuntimeError`` naming the ratio reached if ``max_steps`` are not enough. ``sim``: a
    `Simulation`, or a `dem.DistributedSimulation` (collective: every rank calls the
    controllers at the same steps, and a `ServoWall` reads its wall's force summed over
    the ranks, so every rank moves the wall alike).
    """
    if not 0 < tol < 1:
        raise ValueError(f"tol must lie in (0, 1), got {tol!r}")
    c = 0.02 / sim.dt if damping is None else float(damping)
    if not c >= 0:
        raise ValueError(f"damping must be >= 0 1/s, got {damping!r}")
    decay = math.exp(-c * sim.dt)
    removed0 = sim.damping_removed
    measure, ratio = ratio, math.inf
    hook = None
    if controllers:
        # the controllers act before every step: before the first here, then after each
        # force pass (the step hook, which also runs after the last step of a block)
        def hook():
            for ctl in controllers:
                ctl(sim)
        hook()
    k, max_steps = 0, int(max_steps)
    while k < max_steps:
        # the steps to the next check in one call (the damping inside `Simulation.step`:
        # no Python between steps)
        k += sim.step(min(check_every - k % check_every, max_steps - k), hook=hook, decay=decay)
        if k % check_every == 0:
            ratio = measure(sim)
            if ratio < tol and all(abs(ctl.target - ctl.stress(sim)) <= tol * abs(ctl.target)
                                   for ctl in controllers if isinstance(ctl, ServoWall)):
                return {"steps": k, "ratio": ratio, "energy_removed": sim.damping_removed - removed0}
    raise RuntimeError(f"dynamic relaxation did not reach an unbalanced-force ratio of {tol:g} in "
                       f"{max_steps} steps (reached {ratio:.3g}); raise max_steps or the damping")
