"""Kinematics of GHOST particles prescribed inside one `Simulation.step` call.

A coupled run drives its GHOST particles at every DEM step of an FE step: the ghosts of the
overlap band move linearly in time between two FE states, a rigid penetrator clump is pushed
at a constant velocity. Written from Python before each ``step(1)`` that cost as much as the
steps themselves (small windows); `Prescribed` hands the motions to ``step(n,
prescribed=...)``, which writes them in its own loop, before each step's drift (where the
Python loop wrote them), so the run is the same to the bit. The work of the contacts on the
prescribed particles is booked as that of any GHOST (`Simulation.energy`, ``work_ghosts``).

Every motion has the form x = base + (c_a a + c_b b) per row, with coefficients (c_a, c_b)
per step of the call (`Interpolated`: 1 - s/n and s/n; `Translated`: the accumulated
offset and 0), evaluated in `_prescribe` in that order of operations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from dem.state import GHOST

__all__ = ["Interpolated", "Prescribed", "Translated"]


def _rows3(name, a, k):
    """(k, 3) float64 copy of a (k, d <= 3) array, zero-padded (2D motions)."""
    a = np.asarray(a, float)
    if a.ndim == 1:
        a = np.broadcast_to(a, (k, a.shape[0]))
    if a.ndim != 2 or a.shape[0] != k or a.shape[1] > 3:
        raise ValueError(f"{name} must have shape ({k}, 3) or ({k}, 2), got {a.shape}")
    out = np.zeros((k, 3))
    out[:, : a.shape[1]] = a
    if not np.isfinite(out).all():
        raise ValueError(f"{name} must be finite")
    return out


@dataclass(frozen=True, eq=False)
class Interpolated:
    """Rows moved linearly in time over the n steps of a call: before step s (1..n),
    ``x = base + ((1 - s/n) start + (s/n) end)`` (the state at the end of step s's drift,
    where its forces are evaluated), ``v = velocity``, and ``omega`` if given (else left).

    rows (k,) int; base, start, end (k, 3) or (k, 2) [m] (e.g. reference positions and the
    FE displacements at the start and end of an FE step); velocity (k, 3) or (k, 2) [m/s]
    (None: (end - start) / (n dt)); omega (k, 3) [rad/s] or None.
    """

    rows: np.ndarray
    base: np.ndarray
    start: np.ndarray
    end: np.ndarray
    velocity: np.ndarray | None = None
    omega: np.ndarray | None = None

    def arrays(self, n: int, dt: float):
        """(a, b, coefficients (n, 2), velocity, omega or None) of `Prescribed.pack`."""
        k = len(self.rows)
        a, b = _rows3("Interpolated.start", self.start, k), _rows3("Interpolated.end", self.end, k)
        v = (b - a) / (n * dt) if self.velocity is None else \
            _rows3("Interpolated.velocity", self.velocity, k)
        f = np.arange(1, n + 1) / n
        return a, b, np.column_stack([1 - f, f]), v, self.omega


@dataclass(frozen=True, eq=False)
class Translated:
    """Rows translated along ``direction`` at ``speed``: before step s (1..n),
    ``x = base + o_s direction`` with ``o_s = o_(s-1) + speed dt`` (accumulated step by
    step, as a caller adding ``speed dt`` to a depth would), ``o_0 = offset``;
    ``v = speed direction``; ``omega`` if given.

    rows (k,) int; base (k, 3) or (k, 2) [m]; direction (3,) (not normalised); offset [m]
    at the start of the call; speed [m/s] along direction; omega (k, 3) [rad/s] or None.
    """

    rows: np.ndarray
    base: np.ndarray
    direction: np.ndarray
    offset: float = 0.0
    speed: float = 0.0
    omega: np.ndarray | None = None

    def offsets(self, n: int, dt: float) -> np.ndarray:
        """o_1 .. o_n (n,) [m] (o_n: the offset the next call starts from)."""
        return np.cumsum(np.r_[float(self.offset), np.full(n, float(self.speed) * dt)])[1:]

    def arrays(self, n: int, dt: float):
        k = len(self.rows)
        d = _rows3("Translated.direction", np.asarray(self.direction, float).reshape(1, -1)
                   .repeat(k, axis=0), k)
        o = self.offsets(n, dt)
        return d, np.zeros((k, 3)), np.column_stack([o, np.zeros(n)]), float(self.speed) * d, \
            self.omega


class Prescribed:
    """Motions (`Interpolated`, `Translated`) of disjoint sets of GHOST rows for one
    ``Simulation.step(n, prescribed=...)`` call."""

    def __init__(self, *motions):
        self.motions = [m for m in motions if m is not None and len(m.rows)]

    def pack(self, n: int, dt: float, kind: np.ndarray):
        """Kernel arrays of `_prescribe` for n steps of dt [s] over particles of ``kind``:
        rows (k,), group (k,), base, a, b, velocity, omega (k, 3), set_omega (k,) bool,
        coefficients (n, groups, 2). Raises ValueError naming a row that is out of range,
        not GHOST (the integrator would move it too) or in two motions."""
        if not self.motions:
            return None
        parts = []
        for q, m in enumerate(self.motions):
            rows = np.asarray(m.rows, np.int64).ravel()
            k = len(rows)
            name = type(m).__name__
            if rows.min() < 0 or rows.max() >= len(kind):
                raise ValueError(f"prescribed {name}.rows must lie in [0, {len(kind)}), got "
                                 f"{rows.min()}..{rows.max()}")
            bad = np.flatnonzero(kind[rows] != GHOST)
            if len(bad):
                raise ValueError(f"prescribed {name}.rows: particle {rows[bad[0]]} is not GHOST "
                                 f"({len(bad)} of {k}); only GHOST particles take a "
                                 "prescribed motion")
            base = _rows3(f"{name}.base", m.base, k)
            a, b, coef, v, om = m.arrays(n, dt)
            setom = om is not None
            om = _rows3(f"{name}.omega", om, k) if setom else np.zeros((k, 3))
            parts.append((rows, np.full(k, q, np.int64), base, a, b, v, om,
                          np.full(k, setom), coef))
        rows = np.concatenate([p[0] for p in parts])
        # (a count over the particles, not np.unique's sort: a coupled run packs every FE step)
        counts = np.bincount(rows, minlength=len(kind))
        if counts.max(initial=0) > 1:
            raise ValueError(f"prescribed: particle {int(np.argmax(counts > 1))} is in two motions")
        cat = [np.ascontiguousarray(np.concatenate([p[j] for p in parts])) for j in range(1, 8)]
        coef = np.ascontiguousarray(np.stack([p[8] for p in parts], axis=1))  # (n, groups, 2)
        return (rows, *cat, coef)


@njit(cache=True)
def _prescribe(s, rows, group, base, a, b, vel, om, setom, coef, x, v, omega):
    """Rows' x = base + (c_a a + c_b b), v, (omega) before step s (0-based) of a call."""
    for k in range(rows.shape[0]):
        i = rows[k]
        ca = coef[s, group[k], 0]
        cb = coef[s, group[k], 1]
        for c in range(3):
            x[i, c] = base[k, c] + (ca * a[k, c] + cb * b[k, c])
            v[i, c] = vel[k, c]
            if setom[k]:
                omega[i, c] = om[k, c]
