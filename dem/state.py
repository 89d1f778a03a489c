"""Particle state as a structure of arrays (3 components always; 2D disks live at z = 0).

Kinds: ``FREE`` particles are integrated; ``GHOST`` particles have their motion prescribed
from outside (the coupling layer writes ``x``, ``v``, ``omega``) but their contact forces
and torques are still computed into ``force``/``torque``; ``FIXED`` particles never move.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dem.errors import OverlapError

__all__ = ["FIXED", "FREE", "GHOST", "Particles"]

FREE, GHOST, FIXED = 0, 1, 2


def _first_bad(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask.reshape(mask.shape[0], -1).any(axis=1))[0])


@dataclass(eq=False)
class Particles:
    """Structure of arrays for n spheres (dim=3) or disks of unit thickness (dim=2).

    Arrays (SI units): ``x, v, omega, force, torque`` (n, 3) [m, m/s, rad/s, N, N m];
    ``radius, mass, inertia`` (n,) [m, kg, kg m^2]; ``material`` (n,) int32 (index into
    the material list of the simulation); ``kind`` (n,) int8 (FREE, GHOST, FIXED).
    In 2D, z components of x, v and x/y components of omega must be zero.
    """

    x: np.ndarray
    v: np.ndarray
    omega: np.ndarray
    radius: np.ndarray
    mass: np.ndarray
    inertia: np.ndarray
    material: np.ndarray
    kind: np.ndarray
    dim: int = 3
    force: np.ndarray = field(init=False)
    torque: np.ndarray = field(init=False)

    def __post_init__(self):
        if self.dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {self.dim!r}")
        self.x = self._vec("x", self.x)
        n = self.x.shape[0]
        self.v = self._vec("v", self.v, n)
        self.omega = self._vec("omega", self.omega, n)
        for name in ("radius", "mass", "inertia"):
            a = np.ascontiguousarray(getattr(self, name), dtype=np.float64)
            if a.shape != (n,):
                raise ValueError(f"{name} must have shape ({n},), got {a.shape}")
            bad = ~(a > 0) | ~np.isfinite(a)
            if bad.any():
                i = _first_bad(bad)
                raise ValueError(f"{name} must be finite and > 0; particle {i} has {a[i]!r}")
            setattr(self, name, a)
        self.material = self._ints("material", self.material, n, np.int32)
        self.kind = self._ints("kind", self.kind, n, np.int8)
        if ((self.kind < FREE) | (self.kind > FIXED)).any():
            i = _first_bad((self.kind < FREE) | (self.kind > FIXED))
            raise ValueError(f"kind must be FREE=0, GHOST=1 or FIXED=2; particle {i} has "
                             f"{self.kind[i]}")
        if self.dim == 2:
            for name, comps in (("x", [2]), ("v", [2]), ("omega", [0, 1])):
                a = getattr(self, name)[:, comps]
                if (a != 0).any():
                    raise ValueError(f"2D: {name}[:, {comps}] must be 0; particle "
                                     f"{_first_bad(a != 0)} is not")
        self.force = np.zeros((n, 3))
        self.torque = np.zeros((n, 3))

    @staticmethod
    def _vec(name, a, n=None):
        a = np.array(a, dtype=np.float64)  # a copy: never alias the caller's arrays
        if a.ndim == 2 and a.shape[1] == 2:
            a = np.column_stack([a, np.zeros(a.shape[0])])
        if a.ndim != 2 or a.shape[1] != 3 or (n is not None and a.shape[0] != n):
            want = "(n, 3)" if n is None else f"({n}, 3)"
            raise ValueError(f"{name} must have shape {want} (or (n, 2) in 2D), got {a.shape}")
        if not np.isfinite(a).all():
            i = _first_bad(~np.isfinite(a))
            raise ValueError(f"{name} must be finite; particle {i} has {a[i]}")
        return np.ascontiguousarray(a)

    @staticmethod
    def _ints(name, a, n, dtype):
        a = np.ascontiguousarray(np.broadcast_to(np.asarray(a), (n,)), dtype=dtype).copy()
        return a

    @property
    def n(self) -> int:
        return self.x.shape[0]

    @classmethod
    def spheres(cls, x, radius, density, dim: int = 3, v=None, omega=None, material=0,
                kind=FREE) -> Particles:
        """Spheres (dim=3: m = 4/3 pi r^3 rho, I = 2/5 m r^2) or disks of unit thickness
        (dim=2: m = pi r^2 rho, I = m r^2 / 2). ``x`` (n, 3) or (n, 2) [m]; ``radius``
        scalar or (n,) [m]; ``density`` scalar or (n,) [kg/m^3]."""
        x = cls._vec("x", x)
        n = x.shape[0]
        r = np.ascontiguousarray(np.broadcast_to(np.asarray(radius, float), (n,))).copy()
        rho = np.broadcast_to(np.asarray(density, float), (n,))
        for name, a in (("radius", r), ("density", rho)):
            bad = ~(a > 0) | ~np.isfinite(a)
            if bad.any():
                i = _first_bad(bad)
                raise ValueError(f"{name} must be finite and > 0; particle {i} has {a[i]!r}")
        if dim == 2:
            m = np.pi * r**2 * rho
            inertia = 0.5 * m * r**2
        else:
            m = 4.0 / 3.0 * np.pi * r**3 * rho
            inertia = 0.4 * m * r**2
        v = np.zeros((n, 3)) if v is None else v
        omega = np.zeros((n, 3)) if omega is None else omega
        return cls(x, v, omega, r, m, inertia, material, kind, dim)

    def check_overlaps(self, allow: bool = False, tol: float = 0.0):
        """Count overlapping pairs and the largest overlap [m].

        Returns ``(count, max_overlap, (i, j))``; raises `OverlapError` if any overlap
        exceeds ``tol`` and ``allow`` is False."""
        from dem.neighbours import build_pairs

        pi, pj = build_pairs(self.x, self.radius, 0.0)
        if len(pi) == 0:
            return 0, 0.0, (-1, -1)
        d = np.linalg.norm(self.x[pj] - self.x[pi], axis=1)
        ov = self.radius[pi] + self.radius[pj] - d
        k = int(np.argmax(ov))
        count = int((ov > tol).sum())
        worst = (int(pi[k]), int(pj[k]))
        if count and not allow:
            raise OverlapError(f"{count} overlapping particle pairs at the start; the largest "
                               f"overlap is {ov[k]:.6g} m between particles {worst} "
                               f"(dem.packing.remove_overlaps(particles) moves the free ones apart, or pass "
                               f"allow_overlap=True to start from it)")
        return count, float(max(ov[k], 0.0)), worst

    def state_dict(self) -> dict:
        """Copies of all arrays (for .npz checkpoints)."""
        keys = ("x", "v", "omega", "radius", "mass", "inertia", "material", "kind",
                "force", "torque")
        d = {k: getattr(self, k).copy() for k in keys}
        d["dim"] = np.int64(self.dim)
        return d

    @classmethod
    def from_state_dict(cls, d) -> Particles:
        p = cls(d["x"], d["v"], d["omega"], d["radius"], d["mass"], d["inertia"],
                d["material"], d["kind"], int(d["dim"]))
        return p
