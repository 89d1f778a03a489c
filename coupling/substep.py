"""The DEM phase of one coupled FE step: ``substeps`` DEM steps in one `dem.Simulation.step`
call, with the ghosts and the penetrator driven inside the engine's step loop.

The ghosts move linearly in time from the FE state they last saw to the newest one (seed
001 §3, ghosts interpolated in time between FE states), the penetrator clump at its constant
velocity; both are written before each DEM step's drift (`dem.prescribed`), where the
coupled loops used to write them from Python before each ``step(1)``. One path for the
coupled penetration, its moving window and the full-DEM reference.
"""

from __future__ import annotations

import numpy as np

from dem.prescribed import Interpolated, Prescribed, Translated

__all__ = ["GhostMotion", "sub_cycle"]


class GhostMotion:
    """The ghosts' motion over one FE step of ``dt_fe`` [s]: particles ``rows`` (k,) at
    ``base + ((1 - f) u_start + f u_end)`` at the fraction f of the step, with velocity
    ``(u_end - u_start) / dt_fe``. base (k, 3) [m] (where the ghosts are when the continuum
    is undeformed); u_start, u_end (k, d) [m] (the FE displacements at the ghosts)."""

    def __init__(self, rows, base, u_start, u_end, dt_fe: float):
        self.rows, self.base, self.u_start, self.u_end = rows, base, u_start, u_end
        self.dt_fe = float(dt_fe)

    def motion(self) -> Interpolated:
        return Interpolated(self.rows, self.base, self.u_start, self.u_end,
                            velocity=(self.u_end - self.u_start) / self.dt_fe)


def sub_cycle(sim, substeps: int, penetrator, depth: float, velocity: float, axis: int,
              ghosts: GhostMotion | None = None, hook=None) -> float:
    """Advance ``sim`` by ``substeps`` DEM steps in one call; returns the new depth [m].

    penetrator: (rows (k,), x0 (k, 3)): the clump's GHOST particles and their positions at
    depth 0 [m]; it is pushed down ``axis`` (its positions ``x0 - depth e_axis``) at
    ``velocity`` [m/s], from ``depth`` [m] on, ``velocity dt`` deeper at each DEM step.
    ghosts: the ghosts' motion over the FE step (None: no ghosts, the full-DEM run).
    hook: called after each DEM step's force pass (`dem.Simulation.step`)."""
    rows, x0 = penetrator
    down = np.eye(3)[axis]
    cone = Translated(rows, x0, down, offset=-depth, speed=-velocity)
    sim.step(substeps, hook=hook, prescribed=Prescribed(cone, None if ghosts is None else ghosts.motion()))
    return -float(cone.offsets(substeps, sim.dt)[-1])
