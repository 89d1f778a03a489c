"""Calibration-chamber and penetrator geometries for penetration scenes (gmsh OCC).

Chambers are continuum meshes refined toward the DE window at the top of the axis:

- ``chamber_2d``: plane-strain box ``[-W/2, W/2] x [-H, 0]`` (ground surface y = 0),
  physical groups ``soil`` (2D), ``top``, ``bottom``, ``left``, ``right``.
- ``chamber_3d``: cylinder of radius R, depth H, axis z (surface z = 0), groups
  ``soil`` (3D), ``top``, ``bottom``, ``side``.
- ``chamber_3d_box``: box ``[-W/2, W/2]^2 x [-H, 0]`` (the full-DEM chamber's shape: plane
  walls), groups ``soil`` (3D), ``top``, ``bottom``, ``left``, ``right`` (normal x),
  ``front``, ``back`` (normal y).

Penetrators are rigid surfaces for the DEM (gmsh surface meshes returned as arrays):

- ``cone_penetrometer``: 60 degree cone (standard 10 cm^2: radius 17.84 mm) with a shaft.
- ``flat_pile``: flat-ended cylinder.

In 2D the penetrator is the closed polyline of its half-plane section.
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import gmsh
import numpy as np

from meshes.distribute import on_rank0

__all__ = ["chamber_2d", "chamber_3d", "chamber_3d_box", "build_chamber", "cone_penetrometer", "flat_pile",
           "STANDARD_CONE_RADIUS"]

STANDARD_CONE_RADIUS = float(np.sqrt(10e-4 / np.pi))  # 10 cm^2 projected area


def _check_positive(**values):
    for name, v in values.items():
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be a positive length in m, got {v!r}")


def _refine_toward(model, entities_dim, entities, h_near, h_far, dist_min, dist_max):
    field = model.mesh.field
    dist = field.add("Distance")
    field.setNumbers(dist, "PointsList" if entities_dim == 0 else "CurvesList", entities)
    thr = field.add("Threshold")
    field.setNumber(thr, "InField", dist)
    field.setNumber(thr, "SizeMin", h_near)
    field.setNumber(thr, "SizeMax", h_far)
    field.setNumber(thr, "DistMin", dist_min)
    field.setNumber(thr, "DistMax", dist_max)
    field.setAsBackgroundMesh(thr)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)


def _check_box(width, depth, window_width, window_depth, h_window, h_far):
    """A box chamber's sizes: positive, the window inside."""
    _check_positive(width=width, depth=depth, window_width=window_width,
                    window_depth=window_depth, h_window=h_window, h_far=h_far)
    if window_width >= width or window_depth >= depth:
        raise ValueError("the DE window must lie inside the chamber (window_width < width, "
                         "window_depth < depth)")


def chamber_2d(model, width: float, depth: float, window_width: float, window_depth: float,
               h_window: float, h_far: float) -> None:
    """Plane-strain chamber refined inside and around the DE window ``|x| < w/2, -d < y < 0``."""
    _check_box(width, depth, window_width, window_depth, h_window, h_far)
    occ = model.occ
    box = occ.addRectangle(-width / 2, -depth, 0, width, depth)
    occ.synchronize()
    groups = {"top": [], "bottom": [], "left": [], "right": []}
    for dim, tag in model.getBoundary([(2, box)], oriented=False):
        x, y, _ = occ.getCenterOfMass(dim, tag)
        key = ("top" if np.isclose(y, 0) else "bottom" if np.isclose(y, -depth)
               else "left" if x < 0 else "right")
        groups[key].append(tag)
    model.addPhysicalGroup(2, [box], tag=1, name="soil")
    for i, (name, tags) in enumerate(groups.items()):
        model.addPhysicalGroup(1, tags, tag=10 + i, name=name)
    # size field: distance to a polyline around the window's sides and bottom
    pts = [occ.addPoint(x, y, 0) for x, y in ((-window_width / 2, 0), (-window_width / 2, -window_depth),
                                               (window_width / 2, -window_depth), (window_width / 2, 0))]
    occ.synchronize()
    lines = [occ.addLine(a, b) for a, b in zip(pts, pts[1:], strict=False)]
    occ.synchronize()
    field = model.mesh.field
    dist = field.add("Distance")
    field.setNumbers(dist, "CurvesList", lines)
    field.setNumber(dist, "Sampling", 100)
    inside = field.add("Box")
    field.setNumber(inside, "VIn", h_window)
    field.setNumber(inside, "VOut", h_far)
    field.setNumber(inside, "XMin", -window_width / 2)
    field.setNumber(inside, "XMax", window_width / 2)
    field.setNumber(inside, "YMin", -window_depth)
    field.setNumber(inside, "YMax", 0.0)
    thr = field.add("Threshold")
    field.setNumber(thr, "InField", dist)
    field.setNumber(thr, "SizeMin", h_window)
    field.setNumber(thr, "SizeMax", h_far)
    field.setNumber(thr, "DistMin", 0.0)
    field.setNumber(thr, "DistMax", max(width, depth) / 3)
    both = field.add("Min")
    field.setNumbers(both, "FieldsList", [inside, thr])
    field.setAsBackgroundMesh(both)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    model.mesh.generate(2)


def chamber_3d(model, radius: float, depth: float, window_radius: float, window_depth: float,
               h_window: float, h_far: float) -> None:
    """Cylindrical chamber (axis z, surface z = 0) refined toward the DE window on the axis."""
    _check_positive(radius=radius, depth=depth, window_radius=window_radius,
                    window_depth=window_depth, h_window=h_window, h_far=h_far)
    if window_radius >= radius or window_depth >= depth:
        raise ValueError("the DE window must lie inside the chamber")
    occ = model.occ
    cyl = occ.addCylinder(0, 0, -depth, 0, 0, depth, radius)
    occ.synchronize()
    groups = {"top": [], "bottom": [], "side": []}
    for dim, tag in model.getBoundary([(3, cyl)], oriented=False):
        _, _, z = occ.getCenterOfMass(dim, tag)
        groups["top" if np.isclose(z, 0) else "bottom" if np.isclose(z, -depth) else "side"].append(tag)
    model.addPhysicalGroup(3, [cyl], tag=1, name="soil")
    for i, (name, tags) in enumerate(groups.items()):
        model.addPhysicalGroup(2, tags, tag=10 + i, name=name)
    field = model.mesh.field
    cyl_field = field.add("Cylinder")
    field.setNumber(cyl_field, "Radius", window_radius)
    field.setNumber(cyl_field, "VIn", h_window)
    field.setNumber(cyl_field, "VOut", h_far)
    field.setNumber(cyl_field, "ZAxis", window_depth)
    field.setNumber(cyl_field, "ZCenter", -window_depth / 2)
    ball = field.add("MathEval")
    # linear growth of the size with the distance from the window
    field.setString(ball, "F", f"{h_window} + 0.5 * Max(0, Sqrt(x*x + y*y) - {window_radius}) "
                               f"+ 0.5 * Max(0, -z - {window_depth})")
    both = field.add("Min")
    field.setNumbers(both, "FieldsList", [cyl_field, ball])
    cap = field.add("MathEval")
    field.setString(cap, "F", str(h_far))
    final = field.add("Min")
    field.setNumbers(final, "FieldsList", [both, cap])
    field.setAsBackgroundMesh(final)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    model.mesh.generate(3)


def chamber_3d_box(model, width: float, depth: float, window_width: float, window_depth: float,
                   h_window: float, h_far: float) -> None:
    """Square chamber (axis z, surface z = 0) refined inside and around the DE window
    ``|x|, |y| < w/2, -d < z < 0``; the size grows linearly with the distance from it."""
    _check_box(width, depth, window_width, window_depth, h_window, h_far)
    occ = model.occ
    box = occ.addBox(-width / 2, -width / 2, -depth, width, width, depth)
    occ.synchronize()
    groups = {"top": [], "bottom": [], "left": [], "right": [], "front": [], "back": []}
    for dim, tag in model.getBoundary([(3, box)], oriented=False):
        x, y, z = occ.getCenterOfMass(dim, tag)
        key = ("top" if np.isclose(z, 0) else "bottom" if np.isclose(z, -depth)
               else "left" if np.isclose(x, -width / 2) else "right" if np.isclose(x, width / 2)
               else "front" if y < 0 else "back")
        groups[key].append(tag)
    model.addPhysicalGroup(3, [box], tag=1, name="soil")
    for i, (name, tags) in enumerate(groups.items()):
        model.addPhysicalGroup(2, tags, tag=10 + i, name=name)
    half = window_width / 2
    size = model.mesh.field.add("MathEval")
    model.mesh.field.setString(size, "F", f"Min({h_far}, {h_window} + 0.5 * Max(0, Max(Abs(x), Abs(y)) - {half})"
                                          f" + 0.5 * Max(0, -z - {window_depth}))")
    model.mesh.field.setAsBackgroundMesh(size)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    model.mesh.generate(3)


def build_chamber(comm: MPI.Comm, dim: int, shape: str = "cylinder", **params):
    """Mesh a chamber on rank 0 and distribute it: returns ``dolfinx.io.gmsh.MeshData``.
    ``shape`` (3D): ``"cylinder"`` (:func:`chamber_3d`) or ``"box"`` (:func:`chamber_3d_box`)."""
    builders = {2: chamber_2d} if dim == 2 else {"cylinder": chamber_3d, "box": chamber_3d_box}
    build = builders[2] if dim == 2 else builders.get(shape)
    if build is None:
        raise ValueError(f"shape must be 'cylinder' or 'box', got {shape!r}")
    return on_rank0(comm, f"chamber_{dim}d", lambda m: build(m, **params), dim)


def _surface_arrays(model, dim):
    """Nodes (n, 3) and simplices (m, dim) of the current model's entities of ``dim``."""
    tags, coords, _ = model.mesh.getNodes()
    index = {int(t): i for i, t in enumerate(tags)}
    etype = 1 if dim == 1 else 2  # 2-node lines or 3-node triangles
    _, node_tags = model.mesh.getElementsByType(etype)
    cells = np.array([index[int(t)] for t in node_tags], dtype=np.int64).reshape(-1, dim + 1)
    return coords.reshape(-1, 3), cells


def _mesh_surface(build, dim: int, h: float):
    initialized = gmsh.isInitialized()
    if not initialized:
        gmsh.initialize()
    gmsh.option.setNumber("General.Terminal", 0)
    try:
        gmsh.model.add("penetrator")
        build(gmsh.model.occ)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", h)
        gmsh.option.setNumber("Mesh.MeshSizeMin", h / 4)
        gmsh.model.mesh.generate(dim)
        return _surface_arrays(gmsh.model, dim)
    finally:
        gmsh.model.remove()
        if not initialized:
            gmsh.finalize()


def cone_penetrometer(dim: int = 3, radius: float = STANDARD_CONE_RADIUS, apex_deg: float = 60.0,
                      shaft_length: float | None = None, h: float | None = None):
    """Surface of a cone penetrometer, tip at the origin pointing down (-y in 2D, -z in 3D).

    Returns ``(points (n, 3), cells)``: triangles (m, 3) in 3D, segments (m, 2) in 2D.
    """
    _check_positive(radius=radius)
    if not 0 < apex_deg < 180:
        raise ValueError(f"apex_deg must lie in (0, 180), got {apex_deg!r}")
    shaft_length = 4 * radius if shaft_length is None else shaft_length
    h = radius / 6 if h is None else h
    _check_positive(shaft_length=shaft_length, h=h)
    cone_height = radius / np.tan(np.radians(apex_deg) / 2)
    if dim == 2:
        def build(occ):
            outline = [(0, 0), (radius, cone_height), (radius, cone_height + shaft_length),
                       (-radius, cone_height + shaft_length), (-radius, cone_height)]
            p = [occ.addPoint(x, y, 0, h) for x, y in outline]
            for a, b in zip(p, p[1:] + p[:1], strict=False):
                occ.addLine(a, b)
        return _mesh_surface(build, 1, h)

    def build(occ):
        cone = occ.addCone(0, 0, 0, 0, 0, cone_height, 0, radius)
        shaft = occ.addCylinder(0, 0, cone_height, 0, 0, shaft_length, radius)
        occ.fuse([(3, cone)], [(3, shaft)])
    return _mesh_surface(build, 2, h)


def flat_pile(dim: int = 3, radius: float = 0.02, length: float = 0.1, h: float | None = None):
    """Surface of a flat-ended pile, base centred at the origin, axis up."""
    _check_positive(radius=radius, length=length)
    h = radius / 6 if h is None else h
    if dim == 2:
        def build(occ):
            outline = [(-radius, 0), (radius, 0), (radius, length), (-radius, length)]
            p = [occ.addPoint(x, y, 0, h) for x, y in outline]
            for a, b in zip(p, p[1:] + p[:1], strict=False):
                occ.addLine(a, b)
        return _mesh_surface(build, 1, h)

    def build(occ):
        occ.addCylinder(0, 0, 0, 0, 0, length, radius)
    return _mesh_surface(build, 2, h)
