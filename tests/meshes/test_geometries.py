"""gmsh geometries: named physical groups, refinement toward the DE window, penetrator surfaces."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh

from meshes import penetration, plate_hole


def volume(domain):
    return domain.comm.allreduce(fem.assemble_scalar(fem.form(1.0 * ufl.dx(domain=domain))), MPI.SUM)


@pytest.mark.mpi
def test_chamber_2d_groups_and_refinement():
    data = penetration.build_chamber(MPI.COMM_WORLD, 2, width=1.0, depth=0.6, window_width=0.2,
                                     window_depth=0.2, h_window=0.02, h_far=0.15)
    names = {n for n, (d, _) in data.physical_groups.items()}
    assert {"soil", "top", "bottom", "left", "right"} <= names
    assert np.isclose(volume(data.mesh), 0.6)
    domain = data.mesh
    h = domain.h(2, np.arange(domain.topology.index_map(2).size_local, dtype=np.int32))
    mid = domain.geometry.x[domain.geometry.dofmaps[0][: len(h)]].mean(axis=1)
    inside = (np.abs(mid[:, 0]) < 0.08) & (mid[:, 1] > -0.18)
    h_in = domain.comm.allreduce(h[inside].max(initial=0.0), MPI.MAX)
    h_out = domain.comm.allreduce(h[~inside].max(initial=0.0), MPI.MAX)
    assert h_in < 0.04 < h_out


def test_chamber_3d_groups():
    data = penetration.build_chamber(MPI.COMM_WORLD, 3, radius=0.3, depth=0.5, window_radius=0.08,
                                     window_depth=0.15, h_window=0.04, h_far=0.15)
    names = {n for n, (d, _) in data.physical_groups.items()}
    assert {"soil", "top", "bottom", "side"} <= names
    # faceted cylinder (h_far = R/2): volume within 5 % of pi R^2 H
    assert abs(volume(data.mesh) - np.pi * 0.3**2 * 0.5) < 0.05 * np.pi * 0.3**2 * 0.5


def test_chamber_3d_box_groups_and_refinement():
    data = penetration.build_chamber(MPI.COMM_WORLD, 3, shape="box", width=0.4, depth=0.3, window_width=0.1,
                                     window_depth=0.1, h_window=0.025, h_far=0.12)
    names = {n for n, (d, _) in data.physical_groups.items()}
    assert {"soil", "top", "bottom", "left", "right", "front", "back"} <= names
    assert np.isclose(volume(data.mesh), 0.4 * 0.4 * 0.3)
    domain = data.mesh
    h = domain.h(3, np.arange(domain.topology.index_map(3).size_local, dtype=np.int32))
    mid = domain.geometry.x[domain.geometry.dofmaps[0][: len(h)]].mean(axis=1)
    inside = (np.abs(mid[:, :2]).max(axis=1) < 0.04) & (mid[:, 2] > -0.08)
    h_in = domain.comm.allreduce(h[inside].max(initial=0.0), MPI.MAX)
    h_out = domain.comm.allreduce(h[~inside].max(initial=0.0), MPI.MAX)
    assert h_in < 0.06 < h_out
    # each side's facets lie in its plane
    x = domain.geometry.x
    for name, (axis, value) in {"left": (0, -0.2), "back": (1, 0.2), "bottom": (2, -0.3)}.items():
        facets = data.facet_tags.find(data.physical_groups[name][1])
        nodes = dmesh.entities_to_geometry(domain, 2, facets)
        assert len(facets) == 0 or np.allclose(x[nodes.ravel(), axis], value)
    with pytest.raises(ValueError, match="shape"):
        penetration.build_chamber(MPI.COMM_WORLD, 3, shape="sphere", width=0.4, depth=0.3, window_width=0.1,
                                  window_depth=0.1, h_window=0.025, h_far=0.12)


def test_bad_window_named():
    with pytest.raises(ValueError, match="window"):
        penetration.build_chamber(MPI.COMM_WORLD, 2, width=1.0, depth=0.6, window_width=2.0,
                                  window_depth=0.2, h_window=0.02, h_far=0.15)
    with pytest.raises(ValueError, match="h_window"):
        penetration.build_chamber(MPI.COMM_WORLD, 2, width=1.0, depth=0.6, window_width=0.2,
                                  window_depth=0.2, h_window=-1, h_far=0.15)


def test_cone_surface_3d_closed_and_sized():
    pts, tri = penetration.cone_penetrometer(3, h=0.004)
    r = penetration.STANDARD_CONE_RADIUS
    # projected area of the cone = 10 cm^2; the tip is the lowest point at the origin
    assert np.isclose(pts[:, 2].min(), 0.0, atol=1e-12)
    assert np.isclose(np.hypot(pts[:, 0], pts[:, 1]).max(), r, rtol=1e-6)
    # closed surface: every edge is shared by exactly two triangles
    edges = np.sort(np.vstack([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)


def test_cone_section_2d():
    pts, seg = penetration.cone_penetrometer(2, radius=0.01)
    assert seg.shape[1] == 2
    assert np.isclose(pts[:, 1].min(), 0.0)
    # 60 degree apex: the flank reaches x = r at y = r / tan 30
    flank = pts[np.isclose(pts[:, 0], 0.01)]
    assert np.isclose(flank[:, 1].min(), 0.01 / np.tan(np.radians(30)))


def test_plate_hole_groups():
    data = plate_hole.build(MPI.COMM_WORLD, a=1.0, W=5.0, h_hole=0.2, h_far=1.0)
    assert {"hole", "symmetry_x", "symmetry_y", "right", "top"} <= set(data.physical_groups)
    assert np.isclose(volume(data.mesh), 25 - np.pi / 4, rtol=2e-3)
