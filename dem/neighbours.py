"""Neighbour search: linked cells + Verlet skin, and contact history carried across rebuilds.

Candidate pairs (i < j) have centre distance < r_i + r_j + skin; the list stays valid until
some particle moved more than skin/2 since the build (then two particles could have closed
the skin between them). Building is O(N): particles are binned into cells of size
2 r_max + skin with a counting sort, each particle scans the 27 (3D) or 9 (2D) cells around
it, first counting, then filling (both ``prange`` over particles, deterministic order).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from dem.contact import HIST

__all__ = ["NeighbourList", "brute_force_pairs", "build_pairs", "build_periodic_pairs",
           "carry_history", "wall_candidates"]


@njit(cache=True)
def _bin(x, lo, h, nc):
    n = x.shape[0]
    cell = np.empty(n, np.int64)
    for i in range(n):
        cx = min(max(int((x[i, 0] - lo[0]) / h), 0), nc[0] - 1)
        cy = min(max(int((x[i, 1] - lo[1]) / h), 0), nc[1] - 1)
        cz = min(max(int((x[i, 2] - lo[2]) / h), 0), nc[2] - 1)
        cell[i] = (cz * nc[1] + cy) * nc[0] + cx
    start = np.zeros(nc[0] * nc[1] * nc[2] + 1, np.int64)
    for i in range(n):
        start[cell[i] + 1] += 1
    for c in range(start.shape[0] - 1):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):  # stable: ascending particle index within each cell
        order[fill[cell[i]]] = i
        fill[cell[i]] += 1
    return cell, start, order


@njit(cache=True)
def _scan(i, x, radius, skin, cell, start, order, nc, out, pos):
    """Count (out is None-like: pos < 0) or write the partners j > i of particle i."""
    c = cell[i]
    cx = c % nc[0]
    cy = (c // nc[0]) % nc[1]
    cz = c // (nc[0] * nc[1])
    cnt = 0
    for dz in range(-1, 2):
        z = cz + dz
        if z < 0 or z >= nc[2]:
            continue
        for dy in range(-1, 2):
            y = cy + dy
            if y < 0 or y >= nc[1]:
                continue
            for dx in range(-1, 2):
                xx = cx + dx
                if xx < 0 or xx >= nc[0]:
                    continue
                cc = (z * nc[1] + y) * nc[0] + xx
                for s in range(start[cc], start[cc + 1]):
                    j = order[s]
                    if j <= i:
                        continue
                    rx = x[j, 0] - x[i, 0]
                    ry = x[j, 1] - x[i, 1]
                    rz = x[j, 2] - x[i, 2]
                    cut = radius[i] + radius[j] + skin
                    if rx * rx + ry * ry + rz * rz < cut * cut:
                        if pos >= 0:
                            out[pos + cnt] = j
                        cnt += 1
    return cnt


def _pairs_py(x, radius, skin, lo, h, nc, apart, skip, others):
    """Candidate pairs (i < j), pi ascending. ``apart``: no pairs of two ``skip`` rows: a
    skip row scans a second grid holding the ``others`` (the rows not skipped, ascending)
    only, so a dense rigid clump (a penetrator of thousands of overlapping spheres) costs
    its neighbours, not its own pairs (the same grid geometry: row i's cell is the same in
    both)."""
    n = x.shape[0]
    cell, start, order = _bin(x, lo, h, nc)
    start_o, order_o = start, order
    if apart:
        _, start_o, order_o = _bin(x[others], lo, h, nc)
        order_o = others[order_o]
    counts = np.zeros(n + 1, np.int64)
    dummy = np.empty(0, np.int64)
    for i in prange(n):
        if apart and skip[i]:
            counts[i + 1] = _scan(i, x, radius, skin, cell, start_o, order_o, nc, dummy, -1)
        else:
            counts[i + 1] = _scan(i, x, radius, skin, cell, start, order, nc, dummy, -1)
    for i in range(n):
        counts[i + 1] += counts[i]
    pj = np.empty(counts[n], np.int64)
    pi = np.empty(counts[n], np.int64)
    for i in prange(n):
        if apart and skip[i]:
            _scan(i, x, radius, skin, cell, start_o, order_o, nc, pj, counts[i])
        else:
            _scan(i, x, radius, skin, cell, start, order, nc, pj, counts[i])
        for k in range(counts[i], counts[i + 1]):
            pi[k] = i
    return pi, pj


PAIRS_PARALLEL_MIN = 4096  # particles; below, a thread rendezvous costs more than it saves
_pairs = njit(parallel=True, cache=True)(_pairs_py)
_pairs_ser = njit(cache=True)(_pairs_py)
_NO_SKIP = (np.zeros(0, np.bool_), np.zeros(0, np.int64))


@njit(cache=True)
def _scan_periodic(i, x, s, radius, skin, h, cell, start, order, nb, out, img, pos):
    """As `_scan` in a periodic cell: bins wrap around, each neighbour bin is visited once
    (fewer than 3 bins along an axis), and j is seen through its nearest image
    x_j + h k, k = -round(s_j - s_i) (written to img[pos + cnt] when pos >= 0)."""
    c = cell[i]
    b0 = c % nb[0]
    b1 = (c // nb[0]) % nb[1]
    b2 = c // (nb[0] * nb[1])
    cnt = 0
    for o2 in range(-1, 2):
        if (nb[2] == 1 and o2 != 0) or (nb[2] == 2 and o2 == -1):
            continue
        z = (b2 + o2) % nb[2]
        for o1 in range(-1, 2):
            if (nb[1] == 1 and o1 != 0) or (nb[1] == 2 and o1 == -1):
                continue
            y = (b1 + o1) % nb[1]
            for o0 in range(-1, 2):
                if (nb[0] == 1 and o0 != 0) or (nb[0] == 2 and o0 == -1):
                    continue
                xx = (b0 + o0) % nb[0]
                cc = (z * nb[1] + y) * nb[0] + xx
                for q in range(start[cc], start[cc + 1]):
                    j = order[q]
                    if j <= i:
                        continue
                    k0 = -np.floor(s[j, 0] - s[i, 0] + 0.5)
                    k1 = -np.floor(s[j, 1] - s[i, 1] + 0.5)
                    k2 = -np.floor(s[j, 2] - s[i, 2] + 0.5)
                    rx = x[j, 0] - x[i, 0] + h[0, 0] * k0 + h[0, 1] * k1 + h[0, 2] * k2
                    ry = x[j, 1] - x[i, 1] + h[1, 0] * k0 + h[1, 1] * k1 + h[1, 2] * k2
                    rz = x[j, 2] - x[i, 2] + h[2, 0] * k0 + h[2, 1] * k1 + h[2, 2] * k2
                    cut = radius[i] + radius[j] + skin
                    if rx * rx + ry * ry + rz * rz < cut * cut:
                        if pos >= 0:
                            out[pos + cnt] = j
                            img[pos + cnt, 0] = k0
                            img[pos + cnt, 1] = k1
                            img[pos + cnt, 2] = k2
                        cnt += 1
    return cnt


def _pairs_periodic_py(x, s, radius, skin, h, nb):
    n = x.shape[0]
    cell = np.empty(n, np.int64)
    for i in range(n):
        c0 = min(max(int(s[i, 0] * nb[0]), 0), nb[0] - 1)
        c1 = min(max(int(s[i, 1] * nb[1]), 0), nb[1] - 1)
        c2 = min(max(int(s[i, 2] * nb[2]), 0), nb[2] - 1)
        cell[i] = (c2 * nb[1] + c1) * nb[0] + c0
    start = np.zeros(nb[0] * nb[1] * nb[2] + 1, np.int64)
    for i in range(n):
        start[cell[i] + 1] += 1
    for c in range(start.shape[0] - 1):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[cell[i]]] = i
        fill[cell[i]] += 1
    counts = np.zeros(n + 1, np.int64)
    dummy = np.empty(0, np.int64)
    dimg = np.empty((0, 3))
    for i in prange(n):
        counts[i + 1] = _scan_periodic(i, x, s, radius, skin, h, cell, start, order, nb,
                                       dummy, dimg, -1)
    for i in range(n):
        counts[i + 1] += counts[i]
    pj = np.empty(counts[n], np.int64)
    pi = np.empty(counts[n], np.int64)
    img = np.empty((counts[n], 3))
    for i in prange(n):
        _scan_periodic(i, x, s, radius, skin, h, cell, start, order, nb, pj, img, counts[i])
        for k in range(counts[i], counts[i + 1]):
            pi[k] = i
    return pi, pj, img


_pairs_periodic = njit(parallel=True, cache=True)(_pairs_periodic_py)
_pairs_periodic_ser = njit(cache=True)(_pairs_periodic_py)


def build_periodic_pairs(x, radius, skin: float, h, dim: int = 3):
    """Pairs (pi, pj, img) of a periodic cell with column vectors h (3, 3) [m] (periodic
    along the first ``dim`` axes; in 2D h[:, 2] = e_z is not periodic): |x_j + h img - x_i|
    < r_i + r_j + skin, img (m, 3) float integer shifts, one nearest image per pair, i < j,
    sorted by (i, j). x must lie in the cell (fractional coordinates in [0, 1))."""
    n = x.shape[0]
    if n < 2:
        return np.empty(0, np.int64), np.empty(0, np.int64), np.zeros((0, 3))
    hinv = np.linalg.inv(h)
    s = x @ hinv.T
    if dim == 2:
        s[:, 2] = 0.0
    cut = 2.0 * radius.max() + skin
    width = 1.0 / np.linalg.norm(hinv, axis=1)  # distance between opposite faces [m]
    nb = np.ones(3, np.int64)
    for a in range(dim):
        if width[a] <= 2.0 * cut:
            raise ValueError(f"periodic cell too thin along axis {a}: face distance "
                             f"{width[a]:.4g} m must exceed 2 (2 r_max + skin) = {2 * cut:.4g} m "
                             f"(one image per pair)")
        nb[a] = max(1, int(width[a] / cut))
    while np.prod(nb) > 8 * n + 64:
        nb = np.maximum(nb // 2, 1)
    kern = _pairs_periodic if n >= PAIRS_PARALLEL_MIN else _pairs_periodic_ser
    pi, pj, img = kern(x, s, radius, float(skin), np.ascontiguousarray(h), nb)
    key = pi * n + pj
    o = np.argsort(key, kind="stable")
    return pi[o], pj[o], img[o]


@njit(cache=True)
def _sort_runs(pi, pj):
    """Sort pj within each run of equal pi (pi ascending, runs short): the pair list
    ordered by (i, j), as a global sort of the keys i n + j would order it."""
    m = pi.shape[0]
    a = 0
    while a < m:
        b = a + 1
        while b < m and pi[b] == pi[a]:
            b += 1
        for q in range(a + 1, b):  # insertion sort of pj[a:b]
            v = pj[q]
            r = q - 1
            while r >= a and pj[r] > v:
                pj[r + 1] = pj[r]
                r -= 1
            pj[r + 1] = v
        a = b


def build_pairs(x, radius, skin: float, skip=None):
    """Pairs (pi, pj) (m,) int64, i < j, with |x_j - x_i| < r_i + r_j + skin; sorted by
    (i, j). x (n, 3) [m], radius (n,) [m], skin [m] >= 0; ``skip`` (n,) bool or None: no
    pair of two skipped rows (prescribed rows that do not touch each other)."""
    n = x.shape[0]
    if n < 2:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    lo = x.min(axis=0)
    span = x.max(axis=0) - lo
    h = 2.0 * radius.max() + skin
    nc = np.maximum(np.floor(span / h).astype(np.int64) + 1, 1)
    while np.prod(nc) > 8 * n + 64:  # sparse clouds: grow cells, keep memory O(N)
        h *= 2.0
        nc = np.maximum(np.floor(span / h).astype(np.int64) + 1, 1)
    kern = _pairs if n >= PAIRS_PARALLEL_MIN else _pairs_ser
    apart = skip is not None and bool(skip.any())
    if apart:
        skip = np.ascontiguousarray(skip, np.bool_)
    pi, pj = kern(x, radius, float(skin), lo, float(h), nc, apart,
                  *((skip, np.flatnonzero(~skip).astype(np.int64)) if apart else _NO_SKIP))
    _sort_runs(pi, pj)  # pi comes out ascending; j in cell order within each i
    return pi, pj


def brute_force_pairs(x, radius, skin: float):
    """O(N^2) reference of `build_pairs` (tests)."""
    d = np.linalg.norm(x[:, None, :] - x[None, :, :], axis=2)
    cut = radius[:, None] + radius[None, :] + skin
    i, j = np.nonzero(np.triu(d < cut, k=1))
    return i.astype(np.int64), j.astype(np.int64)


@njit(cache=True)
def _wall_candidates(x, radius, wall_p, wall_n, skin):
    nw = wall_p.shape[0]
    off = np.empty(nw)
    for w in range(nw):
        off[w] = wall_p[w, 0] * wall_n[w, 0] + wall_p[w, 1] * wall_n[w, 1] \
            + wall_p[w, 2] * wall_n[w, 2]
    near = np.empty((x.shape[0], nw), np.bool_)
    m = 0
    for i in range(x.shape[0]):
        for w in range(nw):
            d = x[i, 0] * wall_n[w, 0] + x[i, 1] * wall_n[w, 1] + x[i, 2] * wall_n[w, 2] \
                - off[w]
            near[i, w] = d < radius[i] + skin
            m += near[i, w]
    wi = np.empty(m, np.int64)
    ww = np.empty(m, np.int64)
    k = 0
    for i in range(x.shape[0]):
        for w in range(nw):
            if near[i, w]:
                wi[k] = i
                ww[k] = w
                k += 1
    return wi, ww


def wall_candidates(x, radius, wall_p, wall_n, skin: float):
    """(particle, wall) pairs (int64, (m,) each) with distance to the plane < r + skin,
    ordered by particle, then wall."""
    if wall_p.shape[0] == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    return _wall_candidates(np.ascontiguousarray(x, float), np.ascontiguousarray(radius, float),
                            np.ascontiguousarray(wall_p, float),
                            np.ascontiguousarray(wall_n, float), float(skin))


@njit(cache=True)
def _merge_match(old_keys, new_keys, idx):
    """idx[q] = position of new_keys[q] in old_keys or -1, by one merge walk (both strictly
    ascending). Returns False (idx unusable) if new_keys is not strictly ascending."""
    m = old_keys.shape[0]
    a = 0
    for q in range(new_keys.shape[0]):
        k = new_keys[q]
        if q and k <= new_keys[q - 1]:
            return False
        while a < m and old_keys[a] < k:
            a += 1
        idx[q] = a if a < m and old_keys[a] == k else -1
    return True


def carry_history(old_keys, new_keys, *arrays):
    """Per-contact arrays (first axis = contact) re-indexed from the sorted ``old_keys`` to
    ``new_keys``; new contacts get zeros. (A merge walk when new_keys is ascending too,
    else searchsorted: the same result.)"""
    out = [np.zeros((new_keys.shape[0],) + a.shape[1:], a.dtype) for a in arrays]
    if old_keys.shape[0] and new_keys.shape[0]:
        old_keys = np.ascontiguousarray(old_keys, np.int64)
        new_keys = np.ascontiguousarray(new_keys, np.int64)
        idx = np.empty(new_keys.shape[0], np.int64)
        if _merge_match(old_keys, new_keys, idx):
            hit = idx >= 0
        else:
            idx = np.minimum(np.searchsorted(old_keys, new_keys), old_keys.shape[0] - 1)
            hit = old_keys[idx] == new_keys
        for a, b in zip(arrays, out, strict=True):
            b[hit] = a[idx[hit]]
    return out


@njit(cache=True)
def _max_disp2(x, x0):
    """Largest squared displacement [m^2] (serial: cheaper than a thread rendezvous)."""
    d2 = 0.0
    for i in range(x.shape[0]):
        a = x[i, 0] - x0[i, 0]
        b = x[i, 1] - x0[i, 1]
        c = x[i, 2] - x0[i, 2]
        d2 = max(d2, a * a + b * b + c * c)
    return d2


def _max_wall_disp(wp, wp0) -> float:
    """Largest displacement [m] of a wall point since the build: `_max_disp2` (0.4 us a
    call against 4 us for a Python loop over five walls' ``tolist``, once per step)."""
    return math.sqrt(_max_disp2(wp, wp0))


def _history_columns(a, name):
    """A restored contact history with HIST columns: one of 3 (the springs alone, written
    before the dashpot kept the last normal force) gets zero columns, as after an opening."""
    a = a.reshape(len(a), -1) if a.size else np.zeros((len(a), HIST))
    if a.shape[1] == 3:
        a = np.hstack([a, np.zeros((len(a), HIST - 3))])
    if a.shape[1] != HIST:
        raise ValueError(f"state 'contacts.{name}' has {a.shape[1]} columns, the contact history "
                         f"{HIST} (`dem.contact.HIST`)")
    return np.ascontiguousarray(a)


class NeighbourList:
    """Verlet list of particle pairs and particle-wall pairs with their contact history.

    Attributes: ``pi, pj`` (m,) int64; ``img`` (m, 3) periodic image shifts of j (zeros
    without a cell); ``hist`` (m, HIST) contact history (tangential springs [m], then the
    dashpot's history of the last force pass: `dem.contact`); ``slip`` (m,) int8 sliding
    flags; ``etan`` (m,) spring energies [J]; the same for walls as ``wi, ww, whist, wslip,
    wetan``; ``builds`` (number of rebuilds). History is keyed by (i, j), so it survives
    particles wrapping across periodic faces (one image per pair)."""

    def __init__(self, n: int, skin: float):
        if not skin >= 0:
            raise ValueError(f"skin must be >= 0 m, got {skin!r}")
        self.n, self.skin, self.builds = n, float(skin), 0
        e = np.empty(0, np.int64)
        self.pi, self.pj, self.wi, self.ww = e, e.copy(), e.copy(), e.copy()
        self.img = np.zeros((0, 3))
        self.hist, self.whist = np.zeros((0, HIST)), np.zeros((0, HIST))
        self.slip, self.wslip = np.zeros(0, np.int8), np.zeros(0, np.int8)
        self.etan, self.wetan = np.zeros(0), np.zeros(0)
        self._x0 = None
        self._wp0 = None
        self._h0 = None
        self._cut = 0.0

    _PAIR = ("pi", "pj", "img", "hist", "slip", "etan")
    _WALL = ("wi", "ww", "whist", "wslip", "wetan")

    def keep_pairs(self, keep: np.ndarray) -> None:
        """Drop the pair candidates where the bool mask ``keep`` is False (with their history)."""
        self._keep(self._PAIR, keep)

    def keep_walls(self, keep: np.ndarray) -> None:
        """Drop the wall candidates where the bool mask ``keep`` is False (with their history)."""
        self._keep(self._WALL, keep)

    def _keep(self, names, keep):
        if not keep.all():
            for k in names:
                setattr(self, k, getattr(self, k)[keep])

    def state_dict(self) -> dict:
        """Copies of the lists, the contact history, the build positions (``x0``, ``wp0``;
        ``h0`` and ``cut`` in a periodic cell) and ``builds``: where the next rebuild falls
        depends on them. Absent entries (before the first build) are left out."""
        d = {k: getattr(self, k).copy() for k in self._PAIR + self._WALL}
        d.update(n=int(self.n), skin=float(self.skin), builds=int(self.builds),
                 cut=float(self._cut))
        for k in ("x0", "wp0", "h0"):
            a = getattr(self, f"_{k}")
            if a is not None:
                d[k] = a.copy()
        return d

    def load_state(self, d) -> None:
        """Restore a `state_dict`; ValueError naming the entry that does not fit (another
        particle count, or per-contact arrays of different lengths)."""
        if int(d["n"]) != self.n:
            raise ValueError(f"state 'contacts.n' is {int(d['n'])} particles, this list {self.n}")
        for names in (self._PAIR, self._WALL):
            m = len(np.asarray(d[names[0]]))
            for k in names:
                if len(np.asarray(d[k])) != m:
                    raise ValueError(f"state 'contacts.{k}' has {len(np.asarray(d[k]))} rows, "
                                     f"'contacts.{names[0]}' {m}")
        dtype = dict(pi=np.int64, pj=np.int64, wi=np.int64, ww=np.int64, slip=np.int8,
                     wslip=np.int8)
        for k in self._PAIR + self._WALL:
            setattr(self, k, np.array(d[k], dtype.get(k, np.float64)))
        self.img = self.img.reshape(-1, 3)
        self.hist, self.whist = (_history_columns(self.hist, "hist"),
                                  _history_columns(self.whist, "whist"))
        self.skin, self.builds, self._cut = float(d["skin"]), int(d["builds"]), float(d["cut"])
        x0 = d.get("x0")
        if x0 is not None and np.shape(x0) != (self.n, 3):
            raise ValueError(f"state 'contacts.x0' has shape {np.shape(x0)}, this list needs "
                             f"({self.n}, 3)")
        for k in ("x0", "wp0", "h0"):
            setattr(self, f"_{k}", None if d.get(k) is None else np.array(d[k], float))

    def needs_rebuild(self, x, wall_p, cell=None, disp2=None) -> bool:
        """True once two particles (or a particle and a wall) may have closed the skin.
        In a deforming periodic cell the affine part of the motion is taken out of the
        displacements and the stretch of the cell since the build is added instead.
        disp2: the largest squared displacement [m^2] of x since the build if the caller
        has it already (the integrator's drift measures it on the way)."""
        if self._x0 is None:
            return True
        if cell is None:
            d = math.sqrt(_max_disp2(x, self._x0) if disp2 is None else disp2)
            if wall_p.shape[0]:
                d += _max_wall_disp(wall_p, self._wp0)
            return d > 0.5 * self.skin
        m = cell.h @ np.linalg.inv(self._h0)
        d = np.sqrt(_max_disp2(x - cell.origin, (self._x0 - cell.origin) @ m.T))
        stretch = np.linalg.norm(m - np.eye(3), 2) * self._cut
        return 2.0 * d + stretch > self.skin

    def build(self, x, radius, wall_p, wall_n, cell=None, skip=None):
        """Rebuild the lists at positions x (n, 3) [m]; with a `dem.periodic.PeriodicCell`
        the particles are first wrapped into the cell (x modified in place). ``skip`` (n,)
        bool or None: no candidates between two skipped rows (`build_pairs`)."""
        n = self.n
        if cell is None:
            pi, pj = build_pairs(x, radius, self.skin, skip)
            img = np.zeros((len(pi), 3))
        else:
            cell.wrap(x)
            pi, pj, img = build_periodic_pairs(x - cell.origin, radius, self.skin, cell.h,
                                               cell.dim)
            if skip is not None:
                keep = ~(skip[pi] & skip[pj])
                pi, pj, img = pi[keep], pj[keep], img[keep]
            self._h0 = cell.h.copy()
            self._cut = 2.0 * float(radius.max()) + self.skin
        self.hist, self.slip, self.etan = carry_history(
            self.pi * n + self.pj, pi * n + pj, self.hist, self.slip, self.etan)
        self.pi, self.pj, self.img = pi, pj, img
        nw = max(wall_p.shape[0], 1)
        wi, ww = wall_candidates(x, radius, wall_p, wall_n, self.skin)
        self.whist, self.wslip, self.wetan = carry_history(
            self.wi * nw + self.ww, wi * nw + ww, self.whist, self.wslip, self.wetan)
        self.wi, self.ww = wi, ww
        self._x0 = x.copy()
        self._wp0 = wall_p.copy()
        self.builds += 1
