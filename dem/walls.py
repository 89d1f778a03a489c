"""Planar walls: fixed or moving with a prescribed velocity; same contact laws as pairs.

A wall contact uses R* = r, m* = m (infinite wall; LIGGGHTS/LAMMPS). Each (particle, wall)
pair carries its own contact history; the resultant force on each wall is reported.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PlaneWall", "WallSet", "box_walls"]


@dataclass(frozen=True)
class PlaneWall:
    """Plane through ``point`` (3,) [m] with ``normal`` (3,) pointing into the domain
    (normalised here), moving with ``velocity`` (3,) [m/s]; ``material`` indexes the
    simulation's material list; ``rigid``: the wall does not deform; ``free_only``: only
    FREE particles touch it (GHOST ones, a prescribed penetrator, pass through: a loading
    plate the cone pierces, as a PFC wall does not meet another wall).

    Contact of a particle of material a with the wall (`dem.contact.pair_table`):

    - the wall has infinite radius and mass: R* = r, m* = m of the particle, and it keeps
      its prescribed velocity whatever the forces (the resultant is reported, `WallSet`);
    - stiffness: by default the wall deforms like a grain of its material (the pair mixing
      of E*, G*, kn, kt: a wall of the particle's own material is as compliant as the
      particle, E* = E/(2 (1 - nu^2)), kn = kn_a); ``rigid=True`` leaves the particle's
      compliance alone: E* = E_a/(1 - nu_a^2), G* = E_a/(2 (2 - nu_a)(1 + nu_a)),
      kn = 2 kn_a, kt = 2 kt_a;
    - restitution: the mean of the particle's and the wall material's, e = (e_a + e_w)/2,
      rigid or not: the dashpot scales with the stiffness (gamma = 2 |beta(e)| sqrt(k m*),
      Tsuji's form for Hertz), so a normal impact rebounds with e whatever the stiffness
      (the contact ODE's e; at the default step within 1 %, tests/dem/test_restitution.py
      and tests/dem/test_walls.py);
    - friction, rolling friction: the smaller of the two; force clipping if either clips.
    """

    point: tuple
    normal: tuple
    velocity: tuple = (0.0, 0.0, 0.0)
    material: int = 0
    rigid: bool = False
    free_only: bool = False

    def __post_init__(self):
        for name in ("point", "normal", "velocity"):
            a = np.asarray(getattr(self, name), float)
            if a.shape != (3,) or not np.isfinite(a).all():
                raise ValueError(f"PlaneWall.{name} must be 3 finite numbers, got {a!r}")
            object.__setattr__(self, name, tuple(a))
        nn = np.linalg.norm(self.normal)
        if not nn > 0:
            raise ValueError("PlaneWall.normal must be non-zero")
        object.__setattr__(self, "normal", tuple(np.asarray(self.normal) / nn))
        if not (isinstance(self.material, int | np.integer) and self.material >= 0):
            raise ValueError(f"PlaneWall.material must be an int >= 0, got {self.material!r}")
        for name in ("rigid", "free_only"):
            if not isinstance(getattr(self, name), bool | np.bool_):
                raise ValueError(f"PlaneWall.{name} must be True or False, got {getattr(self, name)!r}")


class WallSet:
    """Arrays of the walls in a simulation: ``point, normal, velocity, force`` (nw, 3)
    [m, -, m/s, N], ``material`` (nw,) int32, ``rigid`` and ``free_only`` (nw,) bool
    (set-up, not state: not in `state_dict`). ``point`` advances with ``velocity``; set ``velocity[w]`` from
    outside to drive wall w; ``force[w]`` is the resultant of the particles on wall w at the
    last force evaluation."""

    def __init__(self, walls=()):
        walls = list(walls)
        self.specs = walls
        self.point = np.array([w.point for w in walls], float).reshape(-1, 3)
        self.normal = np.array([w.normal for w in walls], float).reshape(-1, 3)
        self.velocity = np.array([w.velocity for w in walls], float).reshape(-1, 3)
        self.material = np.array([w.material for w in walls], np.int32)
        self.rigid = np.array([bool(w.rigid) for w in walls], bool)
        self.free_only = np.array([bool(w.free_only) for w in walls], bool)
        self.force = np.zeros((len(walls), 3))

    def __len__(self):
        return self.point.shape[0]

    def table_columns(self, nmat: int) -> np.ndarray:
        """(nw,) int32 column of each wall in a `dem.contact.pair_table` of nmat materials:
        its material, or nmat + its material for a rigid wall."""
        return (self.material + nmat * self.rigid).astype(np.int32)

    def state_dict(self) -> dict:
        """Copies of point, normal, velocity, force and material."""
        return {k: getattr(self, k).copy() for k in ("point", "normal", "velocity", "force",
                                                     "material")}

    def load_state(self, d) -> None:
        """Restore a `state_dict` in place; ValueError naming an entry of another shape."""
        for k in ("point", "normal", "velocity", "force", "material"):
            a, new = getattr(self, k), np.asarray(d[k])
            if new.shape != a.shape:
                raise ValueError(f"state 'walls.{k}' has shape {new.shape}, these walls "
                                 f"{a.shape}")
        for k in ("point", "normal", "velocity", "force", "material"):
            getattr(self, k)[...] = np.asarray(d[k])

    def advance(self, dt: float):
        self.point += dt * self.velocity


def box_walls(lo, hi, dim: int = 3, top: bool = False, material: int = 0) -> list[PlaneWall]:
    """Walls of the box [lo, hi] (3,) facing inwards: x and y sides and the bottom z = lo
    (3D) or x sides and the bottom y = lo (2D); ``top`` adds the upper one."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    up = 2 if dim == 3 else 1
    walls = []
    for ax in range(up + 1):
        e = np.eye(3)[ax]
        walls.append(PlaneWall(tuple(lo), tuple(e), material=material))
        if ax != up or top:
            walls.append(PlaneWall(tuple(hi), tuple(-e), material=material))
    return walls
