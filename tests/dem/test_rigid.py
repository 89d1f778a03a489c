"""Rigid triangulated bodies: surface covered by the clump, resultant of the grains on it."""

import numpy as np
import pytest

from dem import ContactMaterial, Particles, Simulation, box_walls
from dem.control import relax
from dem.packing import lattice_packing
from dem.rigid import RigidBody, sample_surface
from meshes.penetration import flat_pile


def test_clump_covers_the_surface():
    pts, tri = flat_pile(3, radius=0.01, length=0.02, h=0.004)
    r_s = 0.002
    x = sample_surface(pts, tri, r_s)
    # every surface vertex is covered (a centre within ~r_s, 2 r_s at edges), every centre is inside
    d = np.min(np.linalg.norm(pts[:, None, :] - x[None, :, :], axis=2), axis=1)
    assert np.all(d < 2.0 * r_s)  # sharp edges are rounded inward by at most ~r_s
    assert np.all(np.hypot(x[:, 0], x[:, 1]) <= 0.01 - 0.9 * r_s)
    assert np.all((x[:, 2] >= 0.9 * r_s) & (x[:, 2] <= 0.02 - 0.9 * r_s))


def test_clump_envelope_is_the_surface_of_a_long_cone_penetrometer():
    """An unstructured triangulation of a shaft is not the convex hull of its vertices: a
    face plane extended along the shaft cuts it, and keeping centres behind every face plane
    put the clump up to 1.5 r_s inside (a 6 mm cone's envelope 5.2 mm wide, its q_c half
    LIGGGHTS' on a mesh cone). The clump's spheres touch the surface from inside, all along."""
    from meshes.penetration import cone_penetrometer

    R, r_s = 0.006, 0.00075
    pts, tri = cone_penetrometer(3, radius=R, apex_deg=60.0, shaft_length=8 * R, h=R / 4)
    x = sample_surface(pts, tri, r_s)
    z_base = R / np.tan(np.radians(30.0))
    top = float(np.max(pts[:, 2]))
    rho = np.hypot(x[:, 0], x[:, 1])
    shaft = (x[:, 2] > z_base + 2 * r_s) & (x[:, 2] < top - 2 * r_s)
    # inside: no sphere beyond the surface
    assert rho.max() <= R - r_s + 1e-9
    # and touching it: the outer centres of the shaft sit r_s inside the facets, which sag
    # up to R (1 - cos(h / 2R)) ~ 0.014 R inside the circle
    outer = rho[shaft] > 0.5 * R
    assert np.all(rho[shaft][outer] > R - r_s - 0.02 * R)
    # every point of the cone face and of the shaft (away from apex and rims) has a sphere
    # surface within a quarter r_s
    rng = np.random.default_rng(3)
    t, th = 0.2 + 0.75 * rng.random(500), 2 * np.pi * rng.random(500)
    face = np.column_stack([t * R * np.cos(th), t * R * np.sin(th), t * z_base])
    zs = z_base + 2 * r_s + (top - z_base - 4 * r_s) * rng.random(500)
    side = np.column_stack([R * np.cos(th), R * np.sin(th), zs])
    for probe in (face, side):
        gap = np.min(np.linalg.norm(probe[:, None, :] - x[None, :, :], axis=2), axis=1) - r_s
        assert gap.max() < 0.25 * r_s


def test_body_thinner_than_the_clump_spheres_is_refused():
    """A disk 3.5 mm thick cannot hold spheres of 2 mm radius inside it: the sampling used to
    give up after its passes and return centres short of the faces; now it names r_s."""
    pts, tri = flat_pile(3, radius=0.01, length=0.0035, h=0.002)
    with pytest.raises(ValueError, match=r"r_s = 0.002 \(clump sphere radius\) is too large"):
        sample_surface(pts, tri, 0.002)
    pts, tri = flat_pile(3, radius=0.01, length=0.0045, h=0.002)
    x = sample_surface(pts, tri, 0.002)  # 0.5 mm to spare: every centre r_s inside
    assert np.all((x[:, 2] >= 0.002 - 1e-9) & (x[:, 2] <= 0.0025 + 1e-9))
    assert np.all(np.hypot(x[:, 0], x[:, 1]) <= 0.008 + 1e-9)


def test_plate_carries_the_weight_of_the_grains():
    """Frictionless grains at rest in the dimples of a plate (a closed thin box, 12 triangles):
    the plate's resultant equals their weight, its torque the moment of their weights."""
    L, H = 0.02, 0.003
    corners = np.array([[x, y, z] for z in (-H, 0.0) for y in (0, L) for x in (0, L)], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tri = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    body = RigidBody.from_surface(corners, tri, r_s=0.0015, reference=(L / 2, L / 2, 0.0))
    # one grain per column, apart from each other, dropped from just above the plate
    g = np.linspace(0.004, L - 0.004, 3)
    x = np.array([[a, b, 0.0012] for a in g for b in g])
    grains = Particles.spheres(x, 1e-3, 2650.0)
    p = body.append_to(grains, 2650.0)
    mat = ContactMaterial(E=1e6, nu=0.25, density=2650.0, friction=0.0, restitution=0.3,
                          law="linear", kn=2e3, kt=0.0)
    sim = Simulation(p, mat, gravity=(0, 0, -9.81), allow_overlap=True)
    # the dimples are shallow (slow sliding mode, w^2 ~ g / (r + r_s)): damp it near-critically
    relax(sim, tol=1e-6, damping=150.0)
    force, torque = body.resultant(sim)
    w = grains.mass * 9.81
    assert force[2] == pytest.approx(-w.sum(), rel=1e-4)
    assert np.abs(force[:2]).max() < 1e-4 * w.sum()
    arm = sim.p.x[: grains.n] - np.array([L / 2, L / 2, 0.0])
    expected = np.cross(arm, np.c_[0 * w, 0 * w, -w]).sum(axis=0)
    assert np.allclose(torque, expected, atol=1e-4 * w.sum() * L)


def test_moving_body_meets_resistance():
    pts, tri = flat_pile(3, radius=0.004, length=0.02, h=0.002)
    x, r = lattice_packing((0, 0, 0), (0.02, 0.02, 0.01), 1e-3, kind="sc", gap=0.01)
    # the pile's end starts half a grain radius above the bed and travels ~2.5 mm
    bottom = float((x[:, 2] + r).max()) + 0.5e-3
    body = RigidBody.from_surface(pts + np.array([0.01, 0.01, bottom]), tri, r_s=0.0007)
    p = body.append_to(Particles.spheres(x, r, 2650.0), 2650.0)
    mat = ContactMaterial(E=1e7, nu=0.25, density=2650.0, friction=0.5, restitution=0.5)
    sim = Simulation(p, mat, walls=box_walls((0, 0, 0), (0.02, 0.02, 0.05)),
                     gravity=(0, 0, -9.81), allow_overlap=True)
    for _ in range(400):
        body.move(sim, (0.0, 0.0, -0.5))
        sim.step(1)
    force, _ = body.resultant(sim)
    assert force[2] > 0.0  # the bed pushes back up
    assert body.displacement[2] == pytest.approx(-0.5 * 400 * sim.dt)
