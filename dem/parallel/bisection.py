"""Recursive coordinate bisection: the default owners of a `DistributedSimulation`'s particles."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["RecursiveBisection"]


@dataclass(frozen=True, eq=False)
class RecursiveBisection:
    """Recursive coordinate bisection: node k splits along ``axis[k]`` at ``cut[k]`` [m];
    ``below[k]``/``above[k]`` are child nodes (>= 0) or leaves ``-1 - rank``. Call it on
    positions (n, 3) to get owner ranks (n,) int64 (a point on a cut goes above)."""

    axis: np.ndarray
    cut: np.ndarray
    below: np.ndarray
    above: np.ndarray
    nranks: int

    @classmethod
    def from_points(cls, x, nranks: int, axes=(0, 1, 2)) -> RecursiveBisection:
        """Cuts giving each of ``nranks`` ranks (about) as many of the points x (n, 3) [m],
        each cut normal to the longest of ``axes`` of the box of the points it splits."""
        if not (isinstance(nranks, int | np.integer) and nranks >= 1):
            raise ValueError(f"nranks must be an int >= 1, got {nranks!r}")
        allowed = np.zeros(3, bool)
        allowed[list(axes)] = True
        x = np.asarray(x, float).reshape(-1, 3)
        nodes = []  # (axis, cut, below, above)

        def split(pts, r0, r1):
            if r1 - r0 == 1:
                return -1 - r0
            k = len(nodes)
            nodes.append(None)
            span = pts.max(axis=0) - pts.min(axis=0) if len(pts) else np.zeros(3)
            ax = int(np.argmax(np.where(allowed, span, -1.0)))
            rm = (r0 + r1) // 2
            c = np.sort(pts[:, ax])
            m = int(round(len(c) * (rm - r0) / (r1 - r0)))
            if len(c) == 0:
                cut = 0.0
            elif m <= 0:
                cut = c[0]
            elif m >= len(c):
                cut = np.nextafter(c[-1], np.inf)
            else:
                cut = 0.5 * (c[m - 1] + c[m])
            lo = pts[:, ax] < cut
            nodes[k] = (ax, float(cut), split(pts[lo], r0, rm), split(pts[~lo], rm, r1))
            return k

        split(x, 0, int(nranks))
        a = np.array(nodes, dtype=object).reshape(-1, 4)
        return cls(a[:, 0].astype(np.int64), a[:, 1].astype(float), a[:, 2].astype(np.int64),
                   a[:, 3].astype(np.int64), int(nranks))

    def __call__(self, x) -> np.ndarray:
        x = np.asarray(x, float).reshape(-1, 3)
        node = np.zeros(x.shape[0], np.int64) if len(self.axis) else np.full(x.shape[0], -1)
        live = node >= 0
        while live.any():
            k = node[live]
            up = x[live, self.axis[k]] >= self.cut[k]
            node[live] = np.where(up, self.above[k], self.below[k])
            live = node >= 0
        return -1 - node


def _cut_axes(gravity):
    """Axes the default bisection may cut normal to: under gravity not its own axis. Grains
    fall and pile up along g, so a cut across g sees them migrate through it and leaves the
    contacts (most of the work) on the rank below; cuts along g stay balanced."""
    g = np.abs(np.asarray(gravity, float))
    return (0, 1, 2) if not g.any() else tuple(a for a in range(3) if a != int(np.argmax(g)))
