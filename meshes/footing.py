"""Half of a soil layer under a strip footing (plane strain, symmetry at x = 0), gmsh OCC.

The layer is ``[0, W] x [-D, 0]``; the footing covers ``0 <= x <= b`` of the surface
(``b`` the half-width). Physical groups: surface ``soil``; curves ``footing``
(0 <= x <= b, y = 0), ``surface`` (b <= x <= W, y = 0), ``symmetry`` (x = 0), ``bottom``
(y = -D), ``right`` (x = W). The element size grows from ``h_edge`` at the footing's edge
(the stress singularity where the failure mechanism starts) to ``h_far`` at distance ``b``
and beyond.
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import gmsh
import numpy as np

from meshes.distribute import on_rank0

__all__ = ["strip_footing", "build"]


def strip_footing(model: gmsh.model, b: float, W: float, D: float, h_edge: float,
                  h_far: float) -> None:
    """Add the half layer to ``model`` and mesh it (2D, triangles)."""
    if not (0 < b < W and D > 0):
        raise ValueError(f"need 0 < b < W and D > 0, got b={b}, W={W}, D={D}")
    if not (0 < h_edge <= h_far):
        raise ValueError(f"mesh sizes must satisfy 0 < h_edge <= h_far, got {h_edge}, {h_far}")
    occ = model.occ
    soil = occ.addRectangle(0, -D, 0, W, D)
    edge = occ.addPoint(b, 0, 0)
    occ.fragment([(2, soil)], [(0, edge)])
    occ.synchronize()
    surfaces = model.getEntities(2)
    groups = {"footing": [], "surface": [], "symmetry": [], "bottom": [], "right": []}
    for _, tag in model.getEntities(1):
        x, y, _ = occ.getCenterOfMass(1, tag)
        if np.isclose(y, 0.0):
            groups["footing" if x < b else "surface"].append(tag)
        elif np.isclose(x, 0.0):
            groups["symmetry"].append(tag)
        elif np.isclose(y, -D):
            groups["bottom"].append(tag)
        elif np.isclose(x, W):
            groups["right"].append(tag)
    model.addPhysicalGroup(2, [s for _, s in surfaces], tag=1, name="soil")
    for i, (name, tags) in enumerate(groups.items()):
        model.addPhysicalGroup(1, tags, tag=10 + i, name=name)
    points = [t for _, t in model.getEntities(0)
              if np.allclose(model.getValue(0, t, []), [b, 0, 0])]
    field = model.mesh.field
    dist = field.add("Distance")
    field.setNumbers(dist, "PointsList", points)
    thr = field.add("Threshold")
    field.setNumber(thr, "InField", dist)
    field.setNumber(thr, "SizeMin", h_edge)
    field.setNumber(thr, "SizeMax", h_far)
    field.setNumber(thr, "DistMin", 0.0)
    field.setNumber(thr, "DistMax", 2 * b)
    field.setAsBackgroundMesh(thr)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    model.mesh.generate(2)


def build(comm: MPI.Comm, b: float, W: float, D: float, h_edge: float, h_far: float):
    """Mesh on ``comm`` (gmsh runs on rank 0): returns ``dolfinx.io.gmsh.MeshData``."""
    return on_rank0(comm, "strip_footing", lambda m: strip_footing(m, b, W, D, h_edge, h_far), 2)
