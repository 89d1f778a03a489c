"""Coupling regions from geometric shapes (seed 001 §2.4.1, DESIGN.md "Coupling").

The DE window is a shape W. With signed distance d(x) to W (negative inside):

- particles with ``d <= 0`` are *free* (B^DE and B^h~), particles with
  ``0 < d <= ghost_width`` are *ghosts* (B^h^: motion prescribed by the FE fields),
  particles further out are not simulated;
- FE dofs with ``d <= -handshake`` are *prescribed* (B^h~: projected from the free
  particles, ``handshake >= 0`` keeps a layer of free FE nodes just inside the window),
  all other FE dofs are free (B^h^ and B^h).

Shapes are small frozen dataclasses with a vectorised ``signed_distance(x)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Ball", "Box", "CouplingRegions", "Shape", "Union"]


def _as_points(x: np.ndarray, dim: int) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] < dim:
        raise ValueError(f"points must have shape (n, >= {dim}), got {x.shape}")
    return x[:, :dim]


@dataclass(frozen=True)
class Box:
    """Axis-aligned box [lo, hi] (2D or 3D) [m]."""

    lo: tuple[float, ...]
    hi: tuple[float, ...]

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.lo, float), np.asarray(self.hi, float)
        if lo.shape != hi.shape or lo.size not in (1, 2, 3):
            raise ValueError(f"Box.lo and Box.hi must be 1-3 coordinates each, got {self.lo}, {self.hi}")
        if not np.all(np.isfinite(lo)) or not np.all(np.isfinite(hi)) or np.any(hi <= lo):
            raise ValueError(f"Box.hi must exceed Box.lo in every coordinate, got {self.lo}, {self.hi}")

    def signed_distance(self, x: np.ndarray) -> np.ndarray:
        """Exact signed Euclidean distance to the box surface, (n,)."""
        lo, hi = np.asarray(self.lo, float), np.asarray(self.hi, float)
        x = _as_points(x, lo.size)
        c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
        q = np.abs(x - c) - h
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        inside = np.minimum(q.max(axis=1), 0.0)
        return outside + inside


@dataclass(frozen=True)
class Ball:
    """Disk (2D) or sphere (3D) of centre ``center`` and radius ``radius`` [m]."""

    center: tuple[float, ...]
    radius: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.radius) and self.radius > 0.0):
            raise ValueError(f"Ball.radius must be > 0, got {self.radius!r}")
        if len(self.center) not in (1, 2, 3):
            raise ValueError(f"Ball.center must have 1-3 coordinates, got {self.center}")

    def signed_distance(self, x: np.ndarray) -> np.ndarray:
        c = np.asarray(self.center, float)
        return np.linalg.norm(_as_points(x, c.size) - c, axis=1) - self.radius


@dataclass(frozen=True)
class Union:
    """The union of boxes (a window with a chimney, :mod:`coupling.apps.penetration.moving_window`).

    ``signed_distance`` is the smallest of the members': exact outside, and inside it is
    the depth below the nearest member's surface, so a point where two boxes meet counts as
    deep inside (the union has no face there). ``lo`` and ``hi`` give the bounding box."""

    boxes: tuple[Box, ...]

    def __post_init__(self) -> None:
        if not self.boxes or not all(isinstance(b, Box) for b in self.boxes):
            raise ValueError(f"Union.boxes must be one or more Box, got {self.boxes!r}")
        if len({len(b.lo) for b in self.boxes}) != 1:
            raise ValueError("Union.boxes must all have the same dimension")

    @property
    def lo(self) -> tuple[float, ...]:
        return tuple(np.min([b.lo for b in self.boxes], axis=0).tolist())

    @property
    def hi(self) -> tuple[float, ...]:
        return tuple(np.max([b.hi for b in self.boxes], axis=0).tolist())

    def signed_distance(self, x: np.ndarray) -> np.ndarray:
        return np.min([b.signed_distance(x) for b in self.boxes], axis=0)


Shape = Box | Ball | Union


@dataclass(frozen=True)
class CouplingRegions:
    """The DE window, the ghost band outside it and the prescribed FE zone inside it.

    Attributes:
        window: shape of the free-particle region (B^DE and B^h~).
        ghost_width: width of the ghost-particle band B^h^ outside the window [m], > 0.
        handshake: depth inside the window beyond which FE dofs are prescribed [m], >= 0.
    """

    window: Shape
    ghost_width: float
    handshake: float = 0.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.ghost_width) and self.ghost_width > 0.0):
            raise ValueError(f"ghost_width must be > 0 m, got {self.ghost_width!r}")
        if not (np.isfinite(self.handshake) and self.handshake >= 0.0):
            raise ValueError(f"handshake must be >= 0 m, got {self.handshake!r}")

    def particle_kinds(self, x: np.ndarray) -> np.ndarray:
        """(n,) int8: 0 free, 1 ghost, -1 outside (not simulated), for centroids x (n, d)."""
        d = self.window.signed_distance(x)
        kind = np.full(d.shape, -1, dtype=np.int8)
        kind[d <= 0.0] = 0
        kind[(d > 0.0) & (d <= self.ghost_width)] = 1
        return kind

    def prescribed_nodes(self, x: np.ndarray, tolerance: float = 1e-9) -> np.ndarray:
        """(n,) bool: FE nodes at x (n, d) whose dofs are projected from particles (B^h~).

        Nodes within ``tolerance`` (relative to the handshake depth, or absolute 1e-12 m when
        it is 0) of the boundary count as inside: dof coordinates computed on different
        partitions differ in the last bits, and a node line on the boundary must be decided
        the same way on every rank count.
        """
        slack = tolerance * max(self.handshake, 1e-3)
        return self.window.signed_distance(x) <= -self.handshake + slack
