"""Initial particle packings in an axis-aligned box: lattices and random sequential addition.

Every routine returns ``(x, radius)`` with ``x`` of shape (n, 3) [m] (2D disks have z = 0)
and ``radius`` of shape (n,) [m]. The dimension follows the box: ``lo``/``hi`` of length 2
give disks, of length 3 spheres. No returned packing has an overlap and every particle lies
inside the box (centre at least one radius from each face).
"""

from __future__ import annotations

import math
import warnings

import numba
import numpy as np

from dem.neighbours import build_pairs

__all__ = ["PackingError", "lattice_packing", "push_apart", "random_packing", "remove_overlaps",
           "solid_fraction"]


class PackingError(ValueError):
    """Random addition gave up below the target; ``x``, ``radius``, ``fraction`` hold the result."""

    def __init__(self, message: str, x: np.ndarray, radius: np.ndarray, fraction: float):
        super().__init__(message)
        self.x, self.radius, self.fraction = x, radius, fraction


def _box(lo, hi) -> tuple[np.ndarray, np.ndarray, int]:
    lo = np.asarray(lo, dtype=np.float64).ravel()
    hi = np.asarray(hi, dtype=np.float64).ravel()
    if lo.shape != hi.shape or lo.size not in (2, 3):
        raise ValueError(f"box lo/hi must both have 2 or 3 entries, got {lo.size} and {hi.size}")
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi > lo)):
        raise ValueError(f"box must satisfy hi > lo (finite) on every axis, got lo={lo}, hi={hi}")
    dim = lo.size
    return np.append(lo, 0.0)[:3], np.append(hi, 0.0)[:3], dim


def _particle_measure(radius: np.ndarray, dim: int) -> np.ndarray:
    return math.pi * radius**2 if dim == 2 else 4.0 / 3.0 * math.pi * radius**3


def solid_fraction(radius, lo, hi) -> float:
    """Solid (3D volume / 2D area) fraction of non-overlapping particles in the box [-]."""
    lo3, hi3, dim = _box(lo, hi)
    size = (hi3 - lo3)[:dim]
    return float(_particle_measure(np.asarray(radius, float), dim).sum() / np.prod(size))


def _lattice_sites(kind: str, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Sites (k, dim) of one unit cell in units of its edges, and the edge ratios (dim,)."""
    if kind == "sc":
        return np.zeros((1, dim)), np.ones(dim)
    if kind == "hex" and dim == 2:
        return np.array([[0.0, 0.0], [0.5, 0.5]]), np.array([1.0, math.sqrt(3.0)])
    if kind == "fcc" and dim == 3:
        return np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]]), np.ones(3)
    raise ValueError(f"lattice kind must be 'sc' (2D/3D), 'hex' (2D) or 'fcc' (3D); got "
                     f"{kind!r} in {dim}D")


def lattice_packing(lo, hi, radius: float, kind: str = "sc", gap: float = 0.0,
                    jitter: float = 0.0, seed: int | None = None):
    """Equal particles on a lattice filling the box ``[lo, hi]``.

    Args:
        lo, hi: box corners [m], 2 (disks) or 3 (spheres) entries.
        radius: particle radius [m], > 0.
        kind: ``"sc"`` simple cubic/square, ``"hex"`` hexagonal (2D), ``"fcc"`` (3D).
        gap: nearest-neighbour spacing is ``2 radius (1 + gap)``; gap >= 0.
        jitter: in [0, 1]; each centre moves uniformly inside a ball of radius
            ``jitter * radius * gap`` (half the free gap at most, so no overlap can appear).
        seed: seed of the jitter.

    Returns:
        x (n, 3) [m], radius (n,) [m].
    """
    lo3, hi3, dim = _box(lo, hi)
    if not (radius > 0 and math.isfinite(radius)):
        raise ValueError(f"radius must be > 0 and finite, got {radius!r}")
    if not gap >= 0:
        raise ValueError(f"gap must be >= 0, got {gap!r}")
    if not 0 <= jitter <= 1:
        raise ValueError(f"jitter must be in [0, 1], got {jitter!r}")
    sites, aspect = _lattice_sites(kind, dim)
    spacing = 2.0 * radius * (1.0 + gap)
    # nearest-neighbour distance of the lattice in units of the cell edge
    nn = {"sc": 1.0, "hex": 1.0, "fcc": math.sqrt(0.5)}[kind]
    edge = spacing / nn * aspect
    # the jitter ball is included in the margin so jittered particles stay inside
    margin = radius * (1.0 + jitter * gap)
    span = (hi3 - lo3)[:dim] - 2.0 * margin
    if np.any(span < 0):
        raise ValueError(f"box {(hi3 - lo3)[:dim]} too small for one particle of radius {radius}")
    ncell = np.floor(span / edge).astype(int) + 1
    grids = np.meshgrid(*[np.arange(k) for k in ncell], indexing="ij")
    corners = np.stack([g.ravel() for g in grids], axis=1) * edge
    pts = (corners[:, None, :] + sites[None, :, :] * edge).reshape(-1, dim)
    pts = pts[np.all(pts <= span + 1e-12 * edge, axis=1)] + lo3[:dim] + margin
    if jitter > 0 and gap > 0:
        rng = np.random.default_rng(seed)
        d = rng.normal(size=pts.shape)
        d /= np.linalg.norm(d, axis=1)[:, None]
        amp = jitter * radius * gap * rng.random(len(pts)) ** (1.0 / dim)
        pts = pts + d * amp[:, None]
    x = np.zeros((len(pts), 3))
    x[:, :dim] = pts
    return x, np.full(len(pts), float(radius))


def _draw_radii(rng, r_min, r_max, distribution, budget, dim):
    """Radii (largest first) until their total measure reaches ``budget``."""
    mid_m = _particle_measure(np.array([0.5 * (r_min + r_max)]), dim)[0]
    out = []
    total = 0.0
    while total < budget:
        k = int(1.2 * (budget - total) / mid_m) + 64
        if distribution == "uniform":
            r = rng.uniform(r_min, r_max, k)
        else:
            # lognormal with r_min, r_max at -/+ 2 standard deviations, truncated
            mu, s = 0.5 * (math.log(r_min) + math.log(r_max)), 0.25 * math.log(r_max / r_min)
            r = np.clip(rng.lognormal(mu, max(s, 1e-300), k), r_min, r_max)
        m = _particle_measure(r, dim)
        c = np.cumsum(m) + total
        stop = np.searchsorted(c, budget) + 1
        out.append(r[:stop])
        total = c[min(stop, len(c)) - 1]
    return np.sort(np.concatenate(out))[::-1]


@numba.njit(cache=True)
def _rsa(radii, lo, hi, dim, cell, nc, max_tries, seed):
    """Random sequential addition with a linked-cell grid; returns placed centres and count."""
    np.random.seed(seed)  # noqa: NPY002 (numba supports only the legacy generator)
    n = radii.size
    x = np.zeros((n, 3))
    head = -np.ones(nc[0] * nc[1] * nc[2], dtype=np.int64)
    nxt = -np.ones(n, dtype=np.int64)
    placed = 0
    for p in range(n):
        r = radii[p]
        for _ in range(max_tries):
            c = np.zeros(3)
            for a in range(dim):
                c[a] = lo[a] + r + np.random.random() * (hi[a] - lo[a] - 2.0 * r)  # noqa: NPY002
            ic = np.zeros(3, dtype=np.int64)
            for a in range(3):
                ic[a] = min(max(int((c[a] - lo[a]) / cell), 0), nc[a] - 1)
            ok = True
            for i in range(max(ic[0] - 1, 0), min(ic[0] + 2, nc[0])):
                for j in range(max(ic[1] - 1, 0), min(ic[1] + 2, nc[1])):
                    for k in range(max(ic[2] - 1, 0), min(ic[2] + 2, nc[2])):
                        q = head[(i * nc[1] + j) * nc[2] + k]
                        while q >= 0 and ok:
                            d2 = 0.0
                            for a in range(3):
                                d2 += (c[a] - x[q, a]) ** 2
                            if d2 < (r + radii[q]) ** 2:
                                ok = False
                            q = nxt[q]
            if ok:
                x[placed] = c
                flat = (ic[0] * nc[1] + ic[1]) * nc[2] + ic[2]
                nxt[placed] = head[flat]
                head[flat] = placed
                radii[placed] = r
                placed += 1
                break
    return x[:placed], placed


def random_packing(lo, hi, r_min: float, r_max: float, target_fraction: float,
                   distribution: str = "uniform", seed: int = 0, max_tries: int = 2000,
                   strict: bool = True):
    """Random sequential addition of disks/spheres (largest first) up to a solid fraction.

    Radii are drawn from ``distribution`` (``"uniform"`` on [r_min, r_max] or ``"lognormal"``
    with r_min/r_max at -/+2 standard deviations, truncated) until their total volume
    (area in 2D) is ``target_fraction`` of the box; each is tried at up to ``max_tries``
    random positions (overlap check on a linked-cell grid of edge 2 r_max) and dropped if
    none is free. RSA jams near 0.38 (3D) / 0.55 (2D) for equal sizes.

    Returns:
        x (n, 3) [m], radius (n,) [m]. If the fraction reached is below 0.99 of the target,
        raises `PackingError` (holding the packing) when ``strict``, else warns.
    """
    lo3, hi3, dim = _box(lo, hi)
    if not (0 < r_min <= r_max and math.isfinite(r_max)):
        raise ValueError(f"radii must satisfy 0 < r_min <= r_max, got r_min={r_min!r}, "
                         f"r_max={r_max!r}")
    if np.any((hi3 - lo3)[:dim] < 2 * r_min):
        raise ValueError(f"box {(hi3 - lo3)[:dim]} too small for one particle of radius {r_min}")
    if not 0 < target_fraction < 1:
        raise ValueError(f"target_fraction must be in (0, 1), got {target_fraction!r}")
    if distribution not in ("uniform", "lognormal"):
        raise ValueError(f"distribution must be 'uniform' or 'lognormal', got {distribution!r}")
    if max_tries < 1:
        raise ValueError(f"max_tries must be >= 1, got {max_tries!r}")
    rng = np.random.default_rng(seed)
    size = (hi3 - lo3)[:dim]
    radii = _draw_radii(rng, r_min, r_max, distribution, target_fraction * np.prod(size), dim)
    radii = radii[np.all(2 * radii[:, None] <= size[None, :], axis=1)].copy()
    cell = 2.0 * r_max
    nc = np.ones(3, dtype=np.int64)
    nc[:dim] = np.maximum(np.floor(size / cell).astype(np.int64), 1)
    x, placed = _rsa(radii, lo3, hi3, dim, max(cell, float(np.max(size / nc[:dim]))), nc,
                     int(max_tries), int(seed) & 0x7FFFFFFF)
    radius = radii[:placed].copy()
    phi = solid_fraction(radius, lo3[:dim], hi3[:dim])
    if phi < 0.99 * target_fraction:
        msg = (f"random_packing gave up: solid fraction {phi:.4f} reached of target "
               f"{target_fraction:.4f} ({placed} particles placed of {radii.size} drawn)")
        if strict:
            raise PackingError(msg, x, radius, phi)
        warnings.warn(msg, RuntimeWarning, stacklevel=2)
    return x, radius


def push_apart(x, r, movable, tolerance: float, iterations: int):
    """Remove overlaps by moving the ``movable`` particles only (Jacobi projection: each
    overlap is split between two movable particles, or taken by the movable one alone).

    Returns new centres (n, 3), the iterations used and the largest overlap left [m].
    """
    x = x.copy()
    movable = np.asarray(movable, bool)
    worst = 0.0
    for it in range(iterations + 1):
        pi, pj = build_pairs(x, r, 0.0)
        d = x[pj] - x[pi]
        dist = np.linalg.norm(d, axis=1)
        ov = r[pi] + r[pj] - dist
        hit = (ov > 0) & (movable[pi] | movable[pj])
        worst = float(ov[hit].max(initial=0.0))
        if worst <= tolerance or it == iterations:
            return x, it, worst
        pi, pj, n, ov = pi[hit], pj[hit], d[hit] / dist[hit, None], ov[hit]
        both = movable[pi] & movable[pj]
        share_i = np.where(both, 0.5, movable[pi].astype(float))
        share_j = np.where(both, 0.5, movable[pj].astype(float))
        dx = np.zeros_like(x)
        # slightly more than the overlap: the Jacobi sweep otherwise converges only linearly
        np.add.at(dx, pi, -(1.01 * share_i * ov)[:, None] * n)
        np.add.at(dx, pj, (1.01 * share_j * ov)[:, None] * n)
        x += dx
    return x, iterations, worst


def remove_overlaps(particles, tolerance: float | None = None,
                    iterations: int = 1000) -> tuple[int, float]:
    """Move the FREE ``particles`` (in place) until no pair overlaps by more than
    ``tolerance`` [m] (default 1e-10 of the largest radius), GHOST and FIXED ones held
    (:func:`push_apart`); for a packing that `dem.Simulation` refuses with an `OverlapError`.
    Returns (iterations, largest overlap
    left [m]); raises `OverlapError` if ``iterations`` were not enough."""
    from dem.errors import OverlapError
    from dem.state import FREE

    movable = particles.kind == FREE
    if tolerance is None:
        tolerance = 1e-10 * float(particles.radius.max())
    x, its, worst = push_apart(particles.x, particles.radius, movable, tolerance, iterations)
    particles.x[:] = x
    if worst > tolerance:
        raise OverlapError(f"remove_overlaps: {iterations} iterations left an overlap of "
                           f"{worst:.3g} m (tolerance {tolerance:.3g} m); raise iterations, or the "
                           "held particles overlap each other")
    return its, worst
