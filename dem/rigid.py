"""Rigid bodies from triangulated surfaces (gmsh/meshio), as clumps of GHOST spheres.

The surface is covered by spheres of radius ``r_s`` whose centres sit ``r_s`` inside it
(at least ``r_s`` from every triangle), spaced at most ``r_s`` apart, so the clump's envelope
is the surface up to a roughness of ~``r_s``/4; the grains meet it through the engine's own
contact laws and tangential history. The body moves with a prescribed rigid velocity
(written into the GHOST particles each step) and reports the resultant force and torque
the FREE particles exert on it (the clump's own overlapping spheres are left out).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dem.state import FREE, GHOST, Particles

__all__ = ["RigidBody", "sample_surface", "read_surface"]


def read_surface(path):
    """(points (n, 3), triangles (m, 3)) from a surface mesh file (meshio: .msh, .stl, .vtu)."""
    import meshio

    mesh = meshio.read(path)
    tris = [c.data for c in mesh.cells if c.type == "triangle"]
    if not tris:
        raise ValueError(f"{path} holds no triangles (cell types: {[c.type for c in mesh.cells]})")
    return np.asarray(mesh.points, float), np.vstack(tris).astype(np.int64)


def _closest_on_triangles(p, a, b, c):
    """Closest points (m, 3) of triangles (a, b, c) (m, 3 each) to points p (m, 3), row by
    row (Ericson, Real-Time Collision Detection, 5.1.5: the Voronoi region of a vertex, an
    edge or the face)."""
    dot = lambda u, v: np.einsum("ij,ij->i", u, v)  # noqa: E731
    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c
    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        q = a + ab * (vb * denom)[:, None] + ac * (vc * denom)[:, None]
        # the regions in reverse order of Ericson's tests, so that the first that holds wins
        bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        q[bc] = (b + (c - b) * w[:, None])[bc]
        on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        q[on_ac] = (a + ac * (d2 / (d2 - d6))[:, None])[on_ac]
        q[(d6 >= 0) & (d5 <= d6)] = c[(d6 >= 0) & (d5 <= d6)]
        on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        q[on_ab] = (a + ab * (d1 / (d1 - d3))[:, None])[on_ab]
    q[(d3 >= 0) & (d4 <= d3)] = b[(d3 >= 0) & (d4 <= d3)]
    q[(d1 <= 0) & (d2 <= 0)] = a[(d1 <= 0) & (d2 <= 0)]
    return q


_PASSES = 20


def _nearest_triangle(x, tree, reach, a, b, c, normal):
    """For each centre: the distance to its nearest triangle, the nearest point, that
    triangle, the unit direction from the point to the centre, and whether the centre lies
    on the outer side of the triangle (on it counts as outside)."""
    near = tree.query_ball_point(x, reach)
    rows = np.repeat(np.arange(len(x)), [len(n) for n in near])
    tris = np.concatenate([np.asarray(n, np.int64) for n in near])
    q = _closest_on_triangles(x[rows], a[tris], b[tris], c[tris])
    dist = np.linalg.norm(x[rows] - q, axis=1)
    order = np.lexsort((dist, rows))
    first = order[np.r_[True, rows[order][1:] != rows[order][:-1]]]
    who, d, q, t = rows[first], dist[first], q[first], tris[first]
    away = (x[who] - q) / np.maximum(d, 1e-300)[:, None]
    out = np.einsum("ij,ij->i", away, normal[t]) > -1e-9
    return who, d, q, t, away, out


def sample_surface(points, triangles, r_s: float):
    """Centres (k, 3) covering the closed surface ``(points, triangles)`` at spacing <= r_s,
    ``r_s`` inside it: each at least ``r_s`` from every triangle and as close to ``r_s`` from
    the nearest as the surface allows, so the clump's envelope is the surface (edges rounded
    inward). Normals are made to point away from the body's centroid, so the body must be
    star-shaped about it (cones, piles, plates). The distance is to the triangles near each
    centre, not to their planes: an unstructured triangulation of a curved surface is not
    the convex hull of its vertices, and a face plane extended along a long shaft cuts it
    (that put a cone penetrometer's clump 1.5 r_s deep inside its surface)."""
    from scipy.spatial import cKDTree

    if not r_s > 0:
        raise ValueError(f"r_s (clump sphere radius) must be > 0, got {r_s!r}")
    P, T = np.asarray(points, float), np.asarray(triangles, np.int64)
    a, b, c = P[T[:, 0]], P[T[:, 1]], P[T[:, 2]]
    normal = np.cross(b - a, c - a)
    centroid = P.mean(axis=0)
    flip = np.einsum("ij,ij->i", normal, (a + b + c) / 3 - centroid) < 0
    normal[flip] *= -1
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    centres = []
    for i in range(len(T)):
        edge = max(np.linalg.norm(b[i] - a[i]), np.linalg.norm(c[i] - b[i]), np.linalg.norm(a[i] - c[i]))
        k = max(1, int(np.ceil(edge / r_s)))
        u, v = np.meshgrid(np.arange(k + 1), np.arange(k + 1), indexing="ij")
        keep = u + v <= k
        u, v = u[keep] / k, v[keep] / k
        pts = a[i] + u[:, None] * (b[i] - a[i]) + v[:, None] * (c[i] - a[i])
        centres.append(pts - r_s * normal[i])
    x = np.vstack(centres)
    # push every centre off the triangles it comes closer to than r_s (at edges and corners,
    # and where neighbouring faces fold inward), along the line from the nearest point
    mid = (a + b + c) / 3
    reach = r_s + float(np.max(np.linalg.norm(np.stack([a, b, c]) - mid[None], axis=2)))
    tree = cKDTree(mid)
    for _ in range(_PASSES):
        who, d, q, t, away, out = _nearest_triangle(x, tree, reach, a, b, c, normal)
        # too close, or on the wrong side of the nearest triangle however far (a centre
        # outside the body by r_s or more is not short of it, but still wrong)
        bad = (d < r_s * (1 - 1e-9)) | out
        if not bad.any():
            break
        # a centre on a face or outside it (an edge's sample pushed off by its own face's
        # normal past the next face): r_s behind the nearest point along that face's normal
        away[out] = -normal[t[out]]
        x[who[bad]] = q[bad] + r_s * away[bad]
    else:
        who, d, q, t, away, out = _nearest_triangle(x, tree, reach, a, b, c, normal)
        # where many faces meet (a cone's apex) the passes bounce between them and end a
        # percent or so short; a centre 5 % short or outside means the body is too thin
        bad = (d < 0.95 * r_s) | out
        if bad.any():
            raise ValueError(
                f"r_s = {r_s:g} (clump sphere radius) is too large for this surface: {int(bad.sum())} of "
                f"{len(x)} centres cannot be kept r_s inside it (closest {d[bad].min():.3g} from a "
                f"triangle after {_PASSES} passes); the body has parts thinner than 2 r_s, use a "
                f"smaller r_s")
    # merge duplicates on shared edges (grid to a tenth of the spacing)
    _, first = np.unique(np.round(x / (0.1 * r_s)).astype(np.int64), axis=0, return_index=True)
    return x[np.sort(first)]


@dataclass
class RigidBody:
    """A clump of GHOST particles ``index`` in a simulation's particle arrays.

    Use :meth:`append_to` to build the particle set (grains + body), then :meth:`move` every
    step before ``sim.step(1)`` and :meth:`resultant` after it.
    """

    x0: np.ndarray           # (k, 3) clump centres at the reference position
    r_s: float
    reference: np.ndarray    # (3,) point the torque is taken about (moves with the body)
    index: np.ndarray | None = None
    displacement: np.ndarray | None = None

    @classmethod
    def from_surface(cls, points, triangles, r_s: float, reference=None) -> RigidBody:
        x0 = sample_surface(points, triangles, r_s)
        ref = np.asarray(points, float).mean(axis=0) if reference is None else np.asarray(reference, float)
        return cls(x0, float(r_s), ref.copy(), None, np.zeros(3))

    def append_to(self, grains: Particles, density: float) -> Particles:
        """A new particle set: the grains followed by this body's GHOST spheres."""
        n = grains.n
        body = Particles.spheres(self.x0, self.r_s, density, dim=grains.dim, kind=GHOST)
        self.index = np.arange(n, n + len(self.x0))
        return Particles(np.vstack([grains.x, body.x]), np.vstack([grains.v, body.v]),
                         np.vstack([grains.omega, body.omega]),
                         np.concatenate([grains.radius, body.radius]),
                         np.concatenate([grains.mass, body.mass]),
                         np.concatenate([grains.inertia, body.inertia]),
                         np.concatenate([grains.material, np.zeros(len(self.x0), np.int32)]),
                         np.concatenate([grains.kind, body.kind]), grains.dim)

    def move(self, sim, velocity, dt: float | None = None) -> None:
        """Translate by ``velocity * dt`` (dt: the simulation's step) and set the spheres'
        velocity; call before ``sim.step(1)``."""
        dt = sim.dt if dt is None else dt
        v = np.asarray(velocity, float).reshape(3)
        self.displacement = self.displacement + v * dt
        p = sim.p
        p.x[self.index] = self.x0 + self.displacement
        p.v[self.index] = v
        p.omega[self.index] = 0.0

    def resultant(self, sim):
        """(force (3,), torque (3,)) the FREE particles exert on the body now [N, N m]."""
        pairs, force = sim.contact_forces()
        p = sim.p
        on_body = np.isin(pairs, self.index)
        free = p.kind[pairs] == FREE
        i_body = on_body[:, 0] & free[:, 1]   # body particle is i: force on i by j (a grain)
        j_body = on_body[:, 1] & free[:, 0]   # body particle is j: force on j = -force on i
        f = np.concatenate([force[i_body], -force[j_body]])
        at = np.concatenate([p.x[pairs[i_body, 0]], p.x[pairs[j_body, 1]]])
        ref = self.reference + self.displacement
        return f.sum(axis=0), np.cross(at - ref, f).sum(axis=0)
