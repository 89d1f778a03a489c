"""Where particle centroids sit in a (distributed) DOLFINx mesh.

A particle belongs to the rank that owns the cell containing its centroid (DESIGN.md,
"Parallel"). :func:`owner_ranks` tells every rank where each of its points must live;
:func:`locate_owned` finds, for points already on their owning rank, the owned cell and
the reference coordinates needed to evaluate FE basis functions there.
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401  (orders MPI before the dolfinx bindings)

import numpy as np

import dolfinx.geometry

__all__ = ["PointsOutsideMesh", "locate_owned", "owner_ranks", "pad_points"]


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
    mesh: dolfinx.mesh.Mesh, points: np.ndarray, padding: float = 1e-10
) -> tuple[np.ndarray, np.ndarray]:
    """Owned cell and reference coordinates of each point (local, not collective).

    Every point must lie in a cell owned by this rank (redistribute with :func:`owner_ranks`
    first). On a facet shared by several owned cells the lowest cell index is taken; the
    basis functions are continuous there, so the choice does not change interpolated values.

    Args:
        mesh: the FE mesh (affine or curved cells).
        points: (n, gdim) particle centroids [m].

    Returns:
        cells (n,) int32 local cell indices and X (n, tdim) reference coordinates.
    """
    x = pad_points(points)
    tdim = mesh.topology.dim
    n_owned = mesh.topology.index_map(tdim).size_local
    cells = np.full(x.shape[0], -1, dtype=np.int32)
    if x.shape[0]:
        tree = dolfinx.geometry.bb_tree(mesh, tdim, padding=padding)
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


def reference_coordinates(mesh: dolfinx.mesh.Mesh, x: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Pull points x (n, 3) back to the reference cell of their cells (n,) -> (n, tdim)."""
    tdim, gdim = mesh.topology.dim, mesh.geometry.dim
    cmap = mesh.geometry.cmaps[0]
    dofmap = mesh.geometry.dofmaps[0]
    X = np.empty((x.shape[0], tdim), dtype=np.float64)
    for i, c in enumerate(cells):
        coords = mesh.geometry.x[dofmap[c], :gdim]
        X[i] = cmap.pull_back(x[i : i + 1, :gdim], coords)[0]
    return X
