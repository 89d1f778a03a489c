"""Point values of FE functions on a distributed mesh (collective)."""

from __future__ import annotations

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
from dolfinx import fem, geometry

__all__ = ["probe"]


def probe(f: fem.Function, points: np.ndarray) -> np.ndarray:
    """Values of ``f`` at ``points`` (n, 3) on every rank, shape (n, value_size).

    Collective. A point on a cell boundary takes the value of the lowest rank that
    finds it (a discontinuous field is single-valued this way, rank-count independently
    only up to the choice of cell). Points outside the mesh raise ``ValueError``.
    """
    domain = f.function_space.mesh
    points = np.ascontiguousarray(np.atleast_2d(points), dtype=np.float64)
    if points.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {points.shape}")
    tdim = domain.topology.dim
    tree = geometry.bb_tree(domain, tdim, padding=1e-12)
    candidates = geometry.compute_collisions_points(tree, points)
    cells = geometry.compute_colliding_cells(domain, candidates, points)
    value_size = int(np.prod(f.function_space.value_shape)) if f.function_space.value_shape else 1
    local = np.full((len(points), value_size), np.nan)
    found = np.full(len(points), domain.comm.size, dtype=np.int32)
    owned_cells = domain.topology.index_map(tdim).size_local
    for i in range(len(points)):
        links = cells.links(i)
        links = links[links < owned_cells]
        if len(links):
            local[i] = f.eval(points[i], links[:1]).reshape(-1)
            found[i] = domain.comm.rank
    first = np.empty_like(found)
    domain.comm.Allreduce(found, first, op=MPI.MIN)
    if np.any(first == domain.comm.size):
        raise ValueError(f"points outside the mesh: {points[first == domain.comm.size].tolist()}")
    mine = np.ascontiguousarray(np.where(first == domain.comm.rank, local.T, 0.0).T)
    values = np.empty_like(mine)
    domain.comm.Allreduce(mine, values, op=MPI.SUM)
    return values
