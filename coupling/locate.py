"""Where particle centroids sit in a (distributed) DOLFINx mesh.

A particle belongs to the rank that owns the cell containing its centroid (DESIGN.md,
"Parallel"). :func:`owner_ranks` tells every rank where each of its points must live;
:func:`locate_owned` finds, for points already on their owning rank, the owned cell and
the reference coordinates needed to evaluate FE basis functions there; :func:`relocate`
updates that for moved points, searching again only for those that left their cell.
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401  (orders MPI before the dolfinx bindings)

import dolfinx.geometry
import numpy as np
from numba import njit

__all__ = ["PointsOutsideMesh", "affine_maps", "cell_tree", "inside_reference", "locate_owned", "owner_ranks",
           "pad_points", "reference_coordinates", "relocate"]


class PointsOutsideMesh(ValueError):
    """Raised when particle centroids are not covered by the FE mesh (or by this rank's part)."""


def pad_points(points: np.ndarray) -> np.ndarray:
    """Return points as a C-contiguous float64 (n, 3) array (2D points get z = 0)."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] not in (1, 2, 3):
        raise ValueError(f"points must have shape (n, 1|2|3), got {points.shape}")
    if not np.all(np.isfinite(points)):
        bad = np.flatnonzero(~np.all(np.isfinite(points), axis=1))
        raise ValueError(f"points contain NaN/inf at indices {bad[:10].tolist()}")
    out = np.zeros((points.shape[0], 3), dtype=np.float64)
    out[:, : points.shape[1]] = points
    return out


def _describe(points: np.ndarray, idx: np.ndarray, limit: int = 5) -> str:
    shown = ", ".join(f"#{i} at {np.array2string(points[i], precision=6)}" for i in idx[:limit])
    more = f" (and {idx.size - limit} more)" if idx.size > limit else ""
    return shown + more


def owner_ranks(mesh: dolfinx.mesh.Mesh, points: np.ndarray, padding: float = 1e-10) -> np.ndarray:
    """Rank owning the cell that contains each point (collective).

    Args:
        mesh: the FE mesh.
        points: (n, gdim) centroids held by this rank (any rank may hold any point).
        padding: absolute bounding-box padding [m]; points on a shared facet go to one rank.

    Returns:
        (n,) int32 owner rank per point.

    Raises:
        PointsOutsideMesh: naming the points no rank's cells contain (on every rank that holds
        such a point; ranks stay in step because the check follows the collective call).
    """
    x = pad_points(points)
    data = dolfinx.geometry.determine_point_ownership(mesh, x, padding)
    owners = np.asarray(data.src_owner, dtype=np.int32)
    outside = np.flatnonzero(owners < 0)
    n_outside = mesh.comm.allreduce(outside.size)
    if n_outside:
        raise PointsOutsideMesh(
            f"{n_outside} particle centroid(s) lie outside the FE mesh "
            f"(the mesh must cover the whole DE window); on rank {mesh.comm.rank}: "
            f"{_describe(x, outside) or 'none'}"
        )
    return owners


def locate_owned(
    mesh: dolfinx.mesh.Mesh, points: np.ndarray, padding: float = 1e-10, tree=None
) -> tuple[np.ndarray, np.ndarray]:
    """Owned cell and reference coordinates of each point (local, not collective).

    Every point must lie in a cell owned by this rank (redistribute with :func:`owner_ranks`
    first). On a facet shared by several owned cells the lowest cell index is taken; the
    basis functions are continuous there, so the choice does not change interpolated values.

    Args:
        mesh: the FE mesh (affine or curved cells).
        points: (n, gdim) particle centroids [m].
        tree: the mesh's cell bounding-box tree (:func:`cell_tree`), kept by a caller whose
            mesh does not move (building it costs more than the search), or None.

    Returns:
        cells (n,) int32 local cell indices and X (n, tdim) reference coordinates.
    """
    x = pad_points(points)
    tdim = mesh.topology.dim
    n_owned = mesh.topology.index_map(tdim).size_local
    cells = np.full(x.shape[0], -1, dtype=np.int32)
    if x.shape[0]:
        tree = tree if tree is not None else cell_tree(mesh, padding)
        candidates = dolfinx.geometry.compute_collisions_points(tree, x)
        colliding = dolfinx.geometry.compute_colliding_cells(mesh, candidates, x)
        for i in range(x.shape[0]):
            links = colliding.links(i)
            links = links[links < n_owned]
            if links.size:
                cells[i] = links.min()
    missing = np.flatnonzero(cells < 0)
    if missing.size:
        raise PointsOutsideMesh(
            f"{missing.size} particle centroid(s) are not in a cell owned by rank "
            f"{mesh.comm.rank} (outside the mesh, or on the wrong rank: redistribute with "
            f"owner_ranks first): {_describe(x, missing)}"
        )
    return cells, reference_coordinates(mesh, x, cells)


_SIMPLICES = ("interval", "triangle", "tetrahedron")


def cell_tree(mesh: dolfinx.mesh.Mesh, padding: float = 1e-10):
    """The bounding-box tree of the mesh's local cells, for :func:`locate_owned` and
    :func:`relocate` on a mesh that does not move (the caller keeps it, as it keeps
    :func:`affine_maps`: a 2D chamber's tree costs ~1 ms, a point search through it microseconds)."""
    return dolfinx.geometry.bb_tree(mesh, mesh.topology.dim, padding=padding)


def _affine(mesh) -> bool:
    return (mesh.geometry.cmaps[0].degree == 1 and mesh.topology.cell_type.name in _SIMPLICES
            and mesh.topology.dim == mesh.geometry.dim)


def affine_maps(mesh: dolfinx.mesh.Mesh):
    """(x_0 (c, gdim), J^-1 (c, tdim, gdim), neighbours (c, tdim + 1)) of every local cell of
    an affine simplex mesh (P1 geometry), for :func:`reference_coordinates` and
    :func:`relocate` on a mesh that does not move (the caller keeps them; they are stale
    once the geometry changes), or None for other meshes. ``neighbours[c, i]``: the owned
    cell across the facet opposite vertex i of owned cell c (-1: a boundary, or a ghost
    cell), for :func:`relocate`'s walk."""
    if not _affine(mesh):
        return None
    gdim = mesh.geometry.dim
    v = mesh.geometry.x[mesh.geometry.dofmaps[0], :gdim]   # (c, tdim + 1, gdim)
    J = np.transpose(v[:, 1:, :] - v[:, :1, :], (0, 2, 1))
    return np.ascontiguousarray(v[:, 0, :]), np.linalg.inv(J), _neighbours(mesh)


def _neighbours(mesh: dolfinx.mesh.Mesh) -> np.ndarray:
    """(c, tdim + 1) int32: the owned cell across the facet opposite vertex i of each owned
    cell (-1 none), matched by the facets' geometry nodes (P1: one node a vertex)."""
    nodes = mesh.geometry.dofmaps[0]
    owned = mesh.topology.index_map(mesh.topology.dim).size_local
    nodes = nodes[:owned]
    nv = nodes.shape[1]
    out = np.full((len(nodes), nv), -1, np.int32)
    # facet opposite vertex i: the other vertices, sorted: a key shared by its two cells
    keys = np.concatenate([np.sort(np.delete(nodes, i, axis=1), axis=1) for i in range(nv)])
    cell = np.tile(np.arange(len(nodes)), nv)
    local = np.repeat(np.arange(nv), len(nodes))
    order = np.lexsort(keys.T[::-1])
    k = keys[order]
    same = np.flatnonzero(np.all(k[1:] == k[:-1], axis=1))   # (interior facets: pairs)
    a, b = order[same], order[same + 1]
    out[cell[a], local[a]] = cell[b]
    out[cell[b], local[b]] = cell[a]
    return out


@njit(cache=True)
def _walk(x, cells, x0, jinv, neighbours, tol, max_steps, X, found):
    """Each point from its cell through the facets it lies beyond (the most negative
    barycentric coordinate's) until a cell holds it (within tol in reference coordinates):
    cells (n,) updated in place, X (n, tdim) its reference coordinates there, found (n,)
    False where the walk met a boundary or ghost cell or ran max_steps."""
    tdim, gdim = jinv.shape[1], jinv.shape[2]
    for p in range(x.shape[0]):
        c = cells[p]
        found[p] = False
        for _ in range(max_steps):
            total = 0.0
            worst, low = 0, 2.0
            for i in range(tdim):
                acc = 0.0
                for j in range(gdim):
                    acc += jinv[c, i, j] * (x[p, j] - x0[c, j])
                X[p, i] = acc
                total += acc
                if acc < low:
                    worst, low = i + 1, acc
            if 1.0 - total < low:
                worst, low = 0, 1.0 - total
            if low >= -tol:
                found[p] = True
                break
            nxt = neighbours[c, worst]
            if nxt < 0:
                break
            c = nxt
        cells[p] = c


def reference_coordinates(mesh: dolfinx.mesh.Mesh, x: np.ndarray, cells: np.ndarray,
                          maps=None) -> np.ndarray:
    """Pull points x (n, 3) back to the reference cell of their cells (n,) -> (n, tdim).

    Affine simplices (P1 geometry) in one vectorised solve ``X = J^-1 (x - x_0)`` (with
    ``maps`` from :func:`affine_maps`: a product, the inverses taken once); other cells
    point by point through the coordinate element (Newton for non-affine maps).
    """
    tdim, gdim = mesh.topology.dim, mesh.geometry.dim
    cmap = mesh.geometry.cmaps[0]
    dofmap = mesh.geometry.dofmaps[0]
    X = np.empty((x.shape[0], tdim), dtype=np.float64)
    if x.shape[0] == 0:
        return X
    if maps is not None:
        x0, Jinv = maps[:2]
        return np.einsum("nij,nj->ni", Jinv[cells], x[:, :gdim] - x0[cells])
    if _affine(mesh):
        v = mesh.geometry.x[dofmap[cells], :gdim]  # (n, tdim + 1, gdim), reference vertex order
        J = np.transpose(v[:, 1:, :] - v[:, :1, :], (0, 2, 1))  # (n, gdim, tdim)
        return np.linalg.solve(J, (x[:, :gdim] - v[:, 0, :])[:, :, None])[:, :, 0]
    for i, c in enumerate(cells):
        coords = mesh.geometry.x[dofmap[c], :gdim]
        X[i] = cmap.pull_back(x[i : i + 1, :gdim], coords)[0]
    return X


def inside_reference(cell_type: str, X: np.ndarray, tol: float = 1e-12) -> np.ndarray:
    """(n,) bool: reference points X (n, tdim) inside the reference cell (closed, within tol)."""
    if cell_type in _SIMPLICES:
        return np.all(X >= -tol, axis=1) & (X.sum(axis=1) <= 1.0 + tol)
    if cell_type in ("quadrilateral", "hexahedron"):
        return np.all((X >= -tol) & (X <= 1.0 + tol), axis=1)
    raise NotImplementedError(f"inside_reference: cell type {cell_type!r}")


def relocate(
    mesh: dolfinx.mesh.Mesh, points: np.ndarray, cells: np.ndarray, padding: float = 1e-10,
    maps=None, tree=None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cells and reference coordinates of moved points, searching only for those that left.

    A point whose reference coordinates in its old cell still lie in the reference cell keeps
    that cell (cheap: one pull-back per point). With ``maps`` the others walk through the
    facets they lie beyond to the owned cell that holds them (numba, up to 8 cells: a grain
    or a cone moved by a fraction of an element); those the walk does not place (a boundary,
    a ghost cell, a longer way) and, without maps, all that left go through the
    bounding-box search among this rank's owned cells (a point on a facet: the lowest
    cell index there; the walk keeps the first cell it reaches). Local, not collective.

    Args:
        mesh: the FE mesh.
        points: (n, gdim) new centroids [m], same points and order as ``cells``.
        cells: (n,) their previous owned local cells.
        maps: :func:`affine_maps` of the mesh, or None.
        tree: :func:`cell_tree` of the mesh, or None (built here when a point left its cell).

    Returns:
        cells (n,) int32, X (n, tdim), changed (n,) bool (cell differs from before) and
        lost (n,) bool (no owned cell contains the point: it left this rank or the mesh; its
        cell and X are meaningless).
    """
    x = pad_points(points)
    cells = np.array(cells, dtype=np.int32)
    if cells.shape != (x.shape[0],):
        raise ValueError(f"cells must have shape ({x.shape[0]},), got {cells.shape}")
    before = cells.copy()
    if maps is not None:   # walk from the old cells through their neighbours (numba)
        X = np.empty((x.shape[0], mesh.topology.dim))
        found = np.empty(x.shape[0], dtype=bool)
        _walk(x, cells, maps[0], maps[1], maps[2], 1e-12, 8, X, found)
        left = np.flatnonzero(~found)
        cells[left] = before[left]
    else:
        X = reference_coordinates(mesh, x, cells, maps)
        left = np.flatnonzero(~inside_reference(mesh.topology.cell_type.name, X, tol=1e-12))
    lost = np.zeros(x.shape[0], dtype=bool)
    if left.size:
        tdim = mesh.topology.dim
        n_owned = mesh.topology.index_map(tdim).size_local
        tree = tree if tree is not None else cell_tree(mesh, padding)
        candidates = dolfinx.geometry.compute_collisions_points(tree, x[left])
        colliding = dolfinx.geometry.compute_colliding_cells(mesh, candidates, x[left])
        for k, i in enumerate(left):
            links = colliding.links(k)
            links = links[links < n_owned]
            if links.size:
                cells[i] = links.min()
            else:
                lost[i] = True
        found = left[~lost[left]]
        X[found] = reference_coordinates(mesh, x[found], cells[found], maps)
    return cells, X, (cells != before) & ~lost, lost
