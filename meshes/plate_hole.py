"""Quarter of a square plate with a central circular hole (plane strain), gmsh OCC.

Physical groups: surface ``plate``; curves ``hole`` (r = a), ``symmetry_x`` (x = 0),
``symmetry_y`` (y = 0), ``right`` (x = W) and ``top`` (y = W). The element size grows
from ``h_hole`` at the hole to ``h_far`` at distance ``W/2``.
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import gmsh
import numpy as np

from meshes.distribute import on_rank0

__all__ = ["plate_with_hole", "build"]


def plate_with_hole(model: gmsh.model, a: float, W: float, h_hole: float, h_far: float,
                    order: int = 1) -> None:
    """Add the quarter plate [0, W]^2 minus the disk r < a to ``model`` and mesh it (2D)."""
    if not (0 < a < W):
        raise ValueError(f"hole radius a must satisfy 0 < a < W (plate half-width), got a={a}, W={W}")
    if not (0 < h_hole <= h_far):
        raise ValueError(f"mesh sizes must satisfy 0 < h_hole <= h_far, got {h_hole}, {h_far}")
    occ = model.occ
    plate = occ.addRectangle(0, 0, 0, W, W)
    hole = occ.addDisk(0, 0, 0, a, a)
    (surface, *_), _ = occ.cut([(2, plate)], [(2, hole)])
    occ.synchronize()
    groups = {"hole": [], "symmetry_x": [], "symmetry_y": [], "right": [], "top": []}
    for dim, tag in model.getBoundary([surface], oriented=False):
        x, y, _ = occ.getCenterOfMass(dim, tag)
        if np.isclose(x, W):
            groups["right"].append(tag)
        elif np.isclose(y, W):
            groups["top"].append(tag)
        elif np.isclose(x, 0.0):
            groups["symmetry_x"].append(tag)
        elif np.isclose(y, 0.0):
            groups["symmetry_y"].append(tag)
        else:
            groups["hole"].append(tag)
    model.addPhysicalGroup(2, [surface[1]], tag=1, name="plate")
    for i, (name, tags) in enumerate(groups.items()):
        model.addPhysicalGroup(1, tags, tag=10 + i, name=name)
    field = model.mesh.field
    dist = field.add("Distance")
    field.setNumbers(dist, "CurvesList", groups["hole"])
    field.setNumber(dist, "Sampling", 200)
    thr = field.add("Threshold")
    field.setNumber(thr, "InField", dist)
    field.setNumber(thr, "SizeMin", h_hole)
    field.setNumber(thr, "SizeMax", h_far)
    field.setNumber(thr, "DistMin", 0.5 * a)
    field.setNumber(thr, "DistMax", W / 2)
    field.setAsBackgroundMesh(thr)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    model.mesh.generate(2)
    model.mesh.setOrder(order)


def build(comm: MPI.Comm, a: float, W: float, h_hole: float, h_far: float, order: int = 1):
    """Mesh on ``comm`` (gmsh runs on rank 0): returns ``dolfinx.io.gmsh.MeshData``."""
    return on_rank0(comm, "plate_hole", lambda m: plate_with_hole(m, a, W, h_hole, h_far, order), 2)
