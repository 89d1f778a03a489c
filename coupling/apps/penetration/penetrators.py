"""Penetrators as clumps of ghost particles: the 2D cone section as disks on its outline, the
3D cone penetrometer or flat pile (gmsh surfaces of :mod:`meshes.penetration`) covered by
spheres (:func:`dem.rigid.sample_surface`, thinned). Tips at the origin, axis up."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from coupling.apps.penetration.coupled import PenetrationParameters

__all__ = ["cone_clump", "penetrator_clump", "tip_height"]


def tip_height(prm: PenetrationParameters) -> float:
    """Height of the tip part [m]: the cone's (radius / tan(apex / 2)); 0 for a flat pile."""
    if prm.shape == "pile":
        return 0.0
    return prm.cone_radius / np.tan(np.radians(prm.apex_deg) / 2)


def cone_clump(radius_cone, apex_deg, shaft_length, r_grain):
    """Centres (k, 3) of ghost disks on a cone-and-shaft outline (tip at the origin), the
    disks' radius, and a mask of the ones on the cone (not the shaft)."""
    rc = 0.5 * r_grain
    h_cone = radius_cone / np.tan(np.radians(apex_deg) / 2)
    pts, on_cone = [], []
    for side in (-1, 1):
        s = np.arange(0.0, np.hypot(radius_cone, h_cone), rc)
        t = s / np.hypot(radius_cone, h_cone)
        pts.append(np.column_stack([side * t * radius_cone, t * h_cone]))
        on_cone.append(np.ones(len(s), bool))
        ys = np.arange(h_cone + rc, h_cone + shaft_length, rc)
        pts.append(np.column_stack([np.full_like(ys, side * radius_cone), ys]))
        on_cone.append(np.zeros(len(ys), bool))
    xy = np.vstack(pts)
    keep = np.unique(np.round(xy / (1e-6 * rc)), axis=0, return_index=True)[1]
    xy, cone = xy[np.sort(keep)], np.concatenate(on_cone)[np.sort(keep)]
    # centres sit inside the outline by rc so that the envelope is the cone surface
    return np.column_stack([xy, np.zeros(len(xy))]), rc, cone


def penetrator_clump(prm: PenetrationParameters, shaft_length: float):
    """3D: centres (k, 3) of ghost spheres covering the cone's or pile's gmsh surface (tip at
    the origin, axis z), their radius (half a grain radius), and the mask of the tip part."""
    from dem.rigid import sample_surface
    from meshes.penetration import cone_penetrometer, flat_pile

    r_s, R = 0.5 * prm.radius, prm.cone_radius
    h = max(R / 4, r_s)   # gmsh's triangle size; the clump is sampled at r_s anyway
    if prm.shape == "cone":
        pts, tri = cone_penetrometer(3, radius=R, apex_deg=prm.apex_deg, shaft_length=shaft_length, h=h)
    else:
        pts, tri = flat_pile(3, radius=R, length=shaft_length, h=h)
    x = _thinned(sample_surface(pts, tri, r_s), 0.8 * r_s)
    # the pile's base layer sits r_s above its end; the next shaft ring ~r_s higher
    tip = x[:, 2] < (tip_height(prm) if prm.shape == "cone" else 1.5 * r_s)
    return x, r_s, tip


def _thinned(x: np.ndarray, spacing: float) -> np.ndarray:
    """Greedy Poisson-disk thinning: keep a centre unless a kept one lies within ``spacing``.
    (Sampling each triangle on its own grid puts several centres per r_s^2; every extra
    sphere of a clump costs ~10 clump-internal pairs per DEM step.)"""
    from scipy.spatial import cKDTree

    pairs = cKDTree(x).query_pairs(spacing, output_type="ndarray")
    pairs = np.sort(pairs, axis=1)
    pairs = pairs[np.lexsort((pairs[:, 0], pairs[:, 1]))]
    starts = np.searchsorted(pairs[:, 1], np.arange(len(x) + 1))
    keep = np.ones(len(x), bool)
    for i in range(len(x)):
        if keep[pairs[starts[i]:starts[i + 1], 0]].any():
            keep[i] = False
    return x[keep]
