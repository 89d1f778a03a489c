"""Penetrators as clumps of ghost particles: the 2D cone section as disks on its outline, the
3D cone penetrometer or flat pile (gmsh surfaces of :mod:`meshes.penetration`) covered by
spheres (:func:`dem.rigid.sample_surface`, thinned). Tips at the origin, axis up."""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from coupling.apps.penetration.parameters import VERTICAL

if TYPE_CHECKING:
    from coupling.apps.penetration.coupled import PenetrationParameters

__all__ = ["cone_clump", "penetrator_clump", "tip_height", "ConeParts", "cone_parts", "cone_record",
           "filtered", "SLEEVE_OVER_DIAMETER"]

# ISO 22476-1: a 10 cm^2 cone with a 150 cm^2 friction sleeve just above it, so the sleeve's
# length is 150 / (4 x 10) = 3.75 cone diameters whatever the cone's size
SLEEVE_OVER_DIAMETER = 3.75


def tip_height(prm: PenetrationParameters) -> float:
    """Height of the tip part [m]: the cone's (radius / tan(apex / 2)); 0 for a flat pile."""
    if prm.shape == "pile":
        return 0.0
    return prm.cone_radius / np.tan(np.radians(prm.apex_deg) / 2)


def cone_clump(radius_cone, apex_deg, shaft_length, r_grain):
    """Centres (k, 3) of ghost disks (radius ``rc`` = half a grain radius) along a
    cone-and-shaft outline (tip at the origin), the disks' radius, and a mask of the ones on
    the cone (not the shaft). The centres sit ``rc`` inside the outline, so the clump's
    envelope is the cone's surface (its apex rounded by ``rc``): the disks centred on the
    outline made a cone ``rc`` wider on each side (8 % for a cone of 6 grain diameters) than
    the width its q_c is divided by."""
    rc = 0.5 * r_grain
    half = np.radians(apex_deg) / 2
    h_cone = radius_cone / np.tan(half)
    slant = np.hypot(radius_cone, h_cone)
    inner = radius_cone - rc
    pts, on_cone = [], []
    for side in (-1, 1):
        t = np.arange(0.0, slant, rc) / slant
        # each face's points moved rc along its inward normal; those past the axis or
        # beyond the shaft's inner line dropped (the apex disk and the shaft's take over)
        xy = np.column_stack([side * (t * radius_cone - rc * np.cos(half)), t * h_cone + rc * np.sin(half)])
        xy = xy[(side * xy[:, 0] > 0) & (np.abs(xy[:, 0]) <= inner)]
        pts.append(xy)
        on_cone.append(np.ones(len(xy), bool))
        # the shaft's line from where it meets the face's inner line
        y0 = inner / np.tan(half) + rc / np.sin(half)
        ys = np.arange(y0, h_cone + shaft_length, rc)
        pts.append(np.column_stack([np.full_like(ys, side * inner), ys]))
        on_cone.append(ys < h_cone)
    pts.append(np.array([[0.0, rc / np.sin(half)]]))     # the apex
    on_cone.append(np.ones(1, bool))
    xy = np.vstack(pts)
    keep = np.unique(np.round(xy / (1e-6 * rc)), axis=0, return_index=True)[1]
    xy, cone = xy[np.sort(keep)], np.concatenate(on_cone)[np.sort(keep)]
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


class ConeParts(NamedTuple):
    """Masks over a penetrator clump's spheres: the tip (cone, or the pile's base) and the
    friction sleeve (the shaft from the cone's base up ``SLEEVE_OVER_DIAMETER`` diameters)."""

    tip: np.ndarray
    sleeve: np.ndarray


def cone_parts(pen: np.ndarray, on_cone: np.ndarray, prm: PenetrationParameters) -> ConeParts:
    """The :class:`ConeParts` of the clump with centres ``pen`` (any rigid placement, axis
    vertical) and tip mask ``on_cone``."""
    z = pen[:, VERTICAL[prm.dim]]
    top = z[on_cone].max() + SLEEVE_OVER_DIAMETER * 2 * prm.cone_radius   # from the cone's base
    return ConeParts(on_cone.copy(), ~on_cone & (z <= top))


def cone_record(prm: PenetrationParameters, force, parts: ConeParts, depth, step, t, **extra) -> dict:
    """History entry of the cone readings as ISO 22476-1 defines them, ``force`` (k, 3) being
    the grains' forces on the clump's spheres: q_c = vertical force on the tip / tip area (2D:
    the cone's width, per unit thickness; 3D: pi R^2); f_s = vertical force on the friction
    sleeve / the sleeve's fixed area (2D: its two sides, 2 L; 3D: 2 pi R L), whatever part of
    it is embedded; the friction ratio R_f = f_s / q_c; ``shaft_force``: the whole shaft's."""
    ax = VERTICAL[prm.dim]
    tip_force = float(force[parts.tip, ax].sum())
    sleeve = float(force[parts.sleeve, ax].sum())
    R = prm.cone_radius
    length = SLEEVE_OVER_DIAMETER * 2 * R
    area, sleeve_area = (2 * R, 2 * length) if prm.dim == 2 else (np.pi * R**2, 2 * np.pi * R * length)
    q_c, f_s = tip_force / area, sleeve / sleeve_area
    return {"step": step, "time": t, "depth": depth, "tip_force": tip_force, "q_c": q_c,
            "sleeve_force": sleeve, "f_s": f_s, "friction_ratio": f_s / q_c if q_c > 0 else 0.0,
            "shaft_force": float(force[~parts.tip, ax].sum()), **extra}


def filtered(history: list[dict], key: str, window: float) -> np.ndarray:
    """``key`` of the history averaged over a centred depth window [m] (records closer than
    ``window / 2`` in depth; ends use what they have): the smoothed profile next to the raw
    one, as CPT logs are shown."""
    depth = np.array([h["depth"] for h in history])
    value = np.array([h[key] for h in history], dtype=float)
    lo = np.searchsorted(depth, depth - window / 2, side="left")
    hi = np.searchsorted(depth, depth + window / 2, side="right")
    cum = np.concatenate([[0.0], np.cumsum(value)])
    return (cum[hi] - cum[lo]) / np.maximum(hi - lo, 1)
