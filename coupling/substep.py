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
    is undeformed); u_start, u_end (k, d) [m] (the FE displacements at the ghosts).

    theta_start, theta_end: the continuum's rotation at the ghosts [rad] ((k,) about z in
    2D, (k, 3) in 3D; the micropolar rotation, or a micromorphic phi's axial vector); the
    ghosts then spin at ``(theta_end - theta_start) / dt_fe`` over the step, the rotation
    prescribed as the translation is (a sphere has no orientation to set: its rotation acts
    on the grains through the contacts' tangential slip, which its spin drives). None: the
    ghosts' spin is left as it is."""

    def __init__(self, rows, base, u_start, u_end, dt_fe: float, theta_start=None, theta_end=None):
        self.rows, self.base, self.u_start, self.u_end = rows, base, u_start, u_end
        self.dt_fe = float(dt_fe)
        if (theta_start is None) != (theta_end is None):
            raise ValueError("GhostMotion: theta_start and theta_end are given together (or neither)")
        self.theta = None if theta_start is None else (theta_start, theta_end)

    def spin(self) -> np.ndarray | None:
        """(k, 3) [rad/s] the ghosts' angular velocity over the step, or None."""
        if self.theta is None:
            return None
        rate = (np.asarray(self.theta[1], float) - np.asarray(self.theta[0], float)) / self.dt_fe
        if rate.ndim == 1:                     # 2D: about z
            return np.column_stack([np.zeros((len(rate), 2)), rate])
        return rate

    def motion(self) -> Interpolated:
        return Interpolated(self.rows, self.base, self.u_start, self.u_end,
                            velocity=(self.u_end - self.u_start) / self.dt_fe, omega=self.spin())


def sub_cycle(sim, substeps: int, penetrator, depth: float, velocity: float, axis: int,
              ghosts: GhostMotion | None = None, hook=None, **step) -> float:
    """Advance ``sim`` by ``substeps`` DEM steps in one call; returns the new depth [m].

    penetrator: (rows (k,), x0 (k, 3)): the clump's GHOST particles and their positions at
    depth 0 [m]; it is pushed down ``axis`` (its positions ``x0 - depth e_axis``) at
    ``velocity`` [m/s], from ``depth`` [m] on, ``velocity dt`` deeper at each DEM step.
    ghosts: the ghosts' motion over the FE step (None: no ghosts, the full-DEM run).
    hook: called after each DEM step's force pass; ``step``: further keyword arguments of
    `dem.Simulation.step` (a drag, a response, a pause between steps)."""
    rows, x0 = penetrator
    down = np.eye(3)[axis]
    cone = Translated(rows, x0, down, offset=-depth, speed=-velocity)
    sim.step(substeps, hook=hook, prescribed=Prescribed(cone, None if ghosts is None else ghosts.motion()),
             **step)
    return -float(cone.offsets(substeps, sim.dt)[-1])
