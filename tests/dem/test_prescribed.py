"""Prescribed GHOST motions inside `Simulation.step` (dem.prescribed): the same bits as
writing the rows from Python before each of n ``step(1)`` calls, trajectory and ledger."""

import numpy as np
import pytest

import dem
from dem.prescribed import Interpolated, Prescribed, Translated

R = 1.0e-3


def scene(**options):
    """2D: 12 x 8 frictional disks resting on a bottom row of GHOST disks (the band) and a
    GHOST 'cone' of 5 disks just above them; gravity; walls at the sides."""
    mat = dem.ContactMaterial(E=2e5, nu=0.25, law="linear", kn=2e5, kt=1e5, density=2650.0,
                              friction=0.5, restitution=0.5)
    rng = np.random.default_rng(3)
    i, j = np.meshgrid(np.arange(12), np.arange(9), indexing="ij")
    x = np.column_stack([((2 * i + (j % 2)) * R * 1.001).ravel(),
                         (j * R * np.sqrt(3) * 1.001).ravel()])
    cone = np.column_stack([np.linspace(8e-3, 12e-3, 5), np.full(5, 8 * np.sqrt(3) * R + 3 * R)])
    x = np.vstack([x, cone])
    n = len(x)
    kind = np.zeros(n, np.int8)
    band = np.flatnonzero(x[:, 1] < 0.5 * R)
    kind[band] = dem.GHOST
    cone_rows = np.arange(n - 5, n)
    kind[cone_rows] = dem.GHOST
    radius = R * (1 - 0.1 * rng.random(n))
    p = dem.Particles.spheres(x, radius, 2650.0, dim=2, kind=kind,
                              v=np.column_stack([rng.normal(0, 0.01, (n, 2)), np.zeros(n)]))
    walls = [dem.PlaneWall((-R, 0, 0), (1, 0, 0)), dem.PlaneWall((25 * R, 0, 0), (-1, 0, 0))]
    sim = dem.Simulation(p, mat, walls, gravity=(0, -9.81, 0), allow_overlap=True, **options)
    return sim, band, cone_rows


def band_motion(band, k):
    """Displacements (k, 2) [m] of the band at the start and end of FE step k: sheared and
    heaved linearly in time."""
    u0 = np.column_stack([1e-5 * k * np.ones(len(band)), 2e-6 * k * np.sin(band)])
    u1 = np.column_stack([1e-5 * (k + 1) * np.ones(len(band)), 2e-6 * (k + 1) * np.sin(band)])
    return u0, u1


def run(fused: bool, calls=4, n=30, speed=3.0):
    """``calls`` FE steps of n DEM steps; the cone (speed [m/s]) alone makes the neighbour
    lists rebuild (its prescribed displacement counts toward the skin)."""
    sim, band, rows = scene()
    base = sim.p.x[band].copy()
    pen0 = sim.p.x[rows].copy()
    dt_fe = n * sim.dt
    down = np.array([0.0, -1.0, 0.0])
    depth = 0.0
    for k in range(calls):
        u0, u1 = band_motion(band, k)
        if fused:
            cone = Translated(rows, pen0, down, offset=depth, speed=speed)
            ghosts = Interpolated(band, base, u0, u1, velocity=(u1 - u0) / dt_fe)
            sim.step(n, prescribed=Prescribed(ghosts, cone))
            depth = float(cone.offsets(n, sim.dt)[-1])
        else:
            for s in range(1, n + 1):
                f = s / n
                sim.p.x[band, :2] = base[:, :2] + ((1 - f) * u0 + f * u1)
                sim.p.v[band, :2] = (u1 - u0) / dt_fe
                depth += speed * sim.dt
                sim.p.x[rows] = pen0 + depth * down
                sim.p.v[rows] = speed * down
                sim.step(1)
    return sim, depth


def test_fused_prescribed_step_equals_python_loop_to_the_bit():
    a, da = run(False)
    b, db = run(True)
    assert da == db
    for key in ("x", "v", "omega", "force", "torque"):
        np.testing.assert_array_equal(getattr(a.p, key), getattr(b.p, key), err_msg=key)
    ea, eb = a.energy(), b.energy()
    assert ea == eb
    assert ea["work_ghosts"] != 0.0  # the prescribed rows did work on the grains
    assert a.nsteps == b.nsteps == 120 and a.time == b.time
    assert a.nl.builds == b.nl.builds > 3


def test_prescribed_motion_lands_on_the_end_state():
    sim, band, rows = scene()
    base = sim.p.x[band].copy()
    u1 = np.full((len(band), 2), 1e-5)
    sim.step(10, prescribed=Prescribed(Interpolated(band, base, np.zeros_like(u1), u1)))
    np.testing.assert_array_equal(sim.p.x[band, :2], base[:, :2] + (0.0 * 0 + 1.0 * u1))
    np.testing.assert_allclose(sim.p.v[band, :2], u1 / (10 * sim.dt), rtol=1e-14)


@pytest.mark.parametrize("bad, match", [("free", "is not GHOST"), ("twice", "two motions"),
                                        ("range", "must lie in")])
def test_prescribed_rows_are_checked(bad, match):
    sim, band, rows = scene()
    free = np.flatnonzero(sim.p.kind == dem.FREE)[:3]
    pick = {"free": free, "twice": band[:2], "range": np.array([sim.p.n])}[bad]
    other = Translated(band[:2], sim.p.x[band[:2]], (0, 1, 0))
    with pytest.raises(ValueError, match=match):
        sim.step(2, prescribed=Prescribed(Translated(pick, np.zeros((len(pick), 3)), (0, 1, 0)),
                                          other))


def test_a_hook_that_changes_the_ghosts_is_refused():
    """The ghosts' rows are gathered into buffers sized at the call's start: a hook that
    holds or frees particles mid-call is refused by name (kinds change between calls)."""
    sim = scene()[0]
    p = sim.p

    def release():
        p.kind[np.flatnonzero(p.kind == dem.GHOST)[0]] = dem.FREE
        sim.kinds_changed()

    with pytest.raises(RuntimeError, match="the hook changed the set of GHOST rows"):
        sim.step(3, hook=release)


def test_prescribed_pairs_skipped_leave_the_reaction_of_the_free_grains():
    """``prescribed_pairs=False``: the FREE grains move to the same bits (contacts of two
    prescribed rows move nobody), and a GHOST row's force is what the FREE grains exert on it:
    over the band it balances the grains' weight on it (they rest on it) once they settle."""
    runs = []
    for pairs in (True, False):
        sim, band, cone = scene(prescribed_pairs=pairs)
        sim.step(400)
        runs.append((sim, band, cone))
    (full, band, cone), (skipped, _, _) = runs
    free = full.p.kind == dem.FREE
    assert np.array_equal(full.p.x[free], skipped.p.x[free])
    assert np.array_equal(full.p.v[free], skipped.p.v[free])
    # the cone's disks overlap each other (1 mm apart): with the pairs their forces include
    # each other's pushes, without them nothing (no grain reaches the cone)
    assert np.abs(full.p.force[cone]).max() > 0
    assert np.all(skipped.p.force[cone] == 0.0)
    # two overlapping ghosts under one grain pressed into both: each ghost feels the grain
    # alone, and the two reactions are the grain's force reversed
    x = np.array([[-0.9 * R, 0, 0], [0.9 * R, 0, 0], [0, 1.6 * R, 0]])
    mat = dem.ContactMaterial(E=2e5, nu=0.25, law="linear", kn=2e5, kt=1e5, density=2650.0,
                              friction=0.5, restitution=0.5)
    for pairs in (True, False):
        p = dem.Particles.spheres(x, np.full(3, R), 2650.0, dim=2,
                                  kind=np.array([dem.GHOST, dem.GHOST, dem.FREE], np.int8))
        sim = dem.Simulation(p, mat, allow_overlap=True, prescribed_pairs=pairs)
        sim.compute_forces()
        f = p.force
        if pairs:
            assert f[0, 0] < 0 and abs(f[0, 0]) > abs(f[1, 0] + f[0, 0])   # pushed apart
        else:
            assert np.allclose(f[0] + f[1], -f[2], rtol=1e-14, atol=0)
            assert f[0, 0] == pytest.approx(-f[1, 0]) and f[0, 0] < 0 and f[0, 1] < 0
