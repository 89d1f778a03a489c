"""`Simulation.step` without a hook runs its steps in one numba call (`dem.fused_steps._steps`)
between neighbour builds and checks; with a hook it goes through the Python loop. Both
must give the same bits: positions, velocities, forces, contact history, walls and every
ledger term, across neighbour rebuilds, blow-up checks, a moving wall, external forces,
GHOST rows and prescribed motions; and the loop is loaded from numba's disk cache."""

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import dem
from dem import integrate
from dem.packing import lattice_packing
from dem.prescribed import Prescribed, Translated


def scene(dim, seed=2):
    """Grains dropped loosely into a box with a moving side wall: contacts open and close,
    the list is rebuilt, the wall does work."""
    rng = np.random.default_rng(seed)
    if dim == 3:
        g = np.stack(np.meshgrid(*[np.arange(6)] * 3, indexing="ij"), -1).reshape(-1, 3)
        x = (g + 0.5) * 2.3e-3 + rng.uniform(-1e-4, 1e-4, g.shape)
        mats = [dem.ContactMaterial(E=2.9e7, nu=0.25, density=2650.0, friction=0.5,
                                    restitution=0.5, limit_force=True, rolling_friction=0.05),
                dem.ContactMaterial(E=5e7, nu=0.3, density=2650.0, friction=0.3,
                                    friction_dynamic=0.2, restitution=0.7)]
        walls = dem.box_walls((0, 0, 0), (14e-3,) * 3)
        r, gravity = 1e-3, (0, 0, -9.81)
    else:
        x, _ = lattice_packing((0, 0), (0.03, 0.03), 1.7e-3, kind="hex")
        x[:, :2] += rng.uniform(-5e-5, 5e-5, (len(x), 2))
        mats = [dem.ContactMaterial(E=1e8, nu=0.25, density=2650.0, friction=0.5,
                                    restitution=0.5, law="linear", kn=2e5, kt=1e5)]
        walls = dem.box_walls((0, 0, 0), (0.03, 0.03, 0), dim=2)
        r, gravity = 1.5e-3, (0, -9.81, 0)
    walls[1] = dem.PlaneWall(walls[1].point, walls[1].normal, velocity=(-0.5, 0, 0))
    v = rng.normal(0, 0.05, x.shape)
    if dim == 2:
        v[:, 2] = 0.0
    p = dem.Particles.spheres(x, r, 2650.0, dim=dim, v=v,
                              material=rng.integers(0, len(mats), len(x)))
    sim = dem.Simulation(p, mats, walls, gravity, check_every=37, skin=0.05 * r)
    f = np.zeros(3)
    f[dim - 1] = -1e-4
    sim.set_external_force(np.arange(0, p.n, 5), f)
    return sim


def same(a, b):
    da, db = a.state_dict(), b.state_dict()
    assert da.keys() == db.keys()
    for k in da:
        assert np.array_equal(np.asarray(da[k]), np.asarray(db[k])), k
    assert a.energy() == b.energy()


def counted(monkeypatch):
    """Count the calls of the fused loop (it must be the path taken without a hook)."""
    calls = []
    kernel = integrate._steps

    def wrapper(*args):
        calls.append(args[0])
        return kernel(*args)

    monkeypatch.setattr(integrate, "_steps", wrapper)  # the name `Simulation._fused` calls
    return calls


@pytest.mark.parametrize("dim", [3, 2])
def test_fused_steps_equal_python_loop(dim, monkeypatch):
    calls = counted(monkeypatch)
    fused, loop = scene(dim), scene(dim)
    for n in (1, 150, 63, 2):
        assert fused.step(n) == n
        assert loop.step(n, hook=lambda: False) == n
        same(fused, loop)
    assert fused.nl.builds > 2  # rebuilds inside calls
    assert len(calls) > fused.nl.builds
    assert fused.energy()["work_external"] != 0.0 and fused.energy()["work_walls"] != 0.0


def test_fused_steps_after_outside_writes():
    """Forces, history and wall velocities written between calls are taken up alike."""
    fused, loop = scene(3), scene(3)
    for sim in (fused, loop):
        sim.step(40, hook=None if sim is fused else (lambda: False))
        sim.walls.velocity[0] = (0.0, 0.0, 0.02)
        sim.nl.hist[:, :3] *= 0.5
        sim.history_replaced()
    fused.step(90)
    loop.step(90, hook=lambda: False)
    same(fused, loop)


def test_fused_steps_with_ghosts_and_prescribed_motion(monkeypatch):
    """GHOST rows (some moved by a prescribed motion with a spin, some held) book the same
    ghost work through the fused loop as through the Python loop."""
    calls = counted(monkeypatch)
    sims = []
    for _ in range(2):
        sim = scene(3)
        sim.set_external_force(None, None)
        p = sim.p
        low = np.flatnonzero(p.x[:, 2] < 2.5e-3)
        p.kind[low] = dem.GHOST
        p.kind[p.n - 3:] = dem.GHOST  # held where they are
        sim.kinds_changed()
        sims.append((sim, low, p.x[low].copy()))
    depth = 0.0
    for n in (70, 1, 45):
        for sim, low, base in sims:
            om = np.tile([0.0, 30.0, 0.0], (len(low), 1))
            move = Prescribed(Translated(low, base, (0, 0, 1), offset=depth, speed=0.2,
                                         omega=om))
            sim.step(n, prescribed=move, hook=None if sim is sims[0][0] else (lambda: False))
        depth += 0.2 * n * sims[0][0].dt
        same(sims[0][0], sims[1][0])
    assert calls and sims[0][0].energy()["work_ghosts"] != 0.0


def test_force_sums_over_the_steps_equal_a_hooks(monkeypatch):
    """``step(sums=(rows, out))`` adds the rows' forces of every force pass to ``out`` in the
    fused loop, the same bits as a hook summing them in the Python loop (a coupling's
    time-averaged reactions on its ghosts); bad arguments are named."""
    calls = counted(monkeypatch)
    fused, loop = scene(3), scene(3)
    rows = np.arange(3, fused.p.n, 7)
    out, total = np.zeros((len(rows), 3)), np.zeros((len(rows), 3))

    def add():
        total[:] += loop.p.force[rows]

    for n in (40, 1, 75):
        fused.step(n, sums=(rows, out))
        loop.step(n, hook=add)
        same(fused, loop)
        assert np.array_equal(out, total)
    assert calls and np.abs(out).max() > 0
    with pytest.raises(ValueError, match="sums' rows must be int64"):
        fused.step(1, sums=(rows.astype(np.int32), out))
    with pytest.raises(ValueError, match=rf"sums' out must be .* shape \({len(rows)}, 3\)"):
        fused.step(1, sums=(rows, np.zeros((len(rows), 2))))


CACHE_SCRIPT = textwrap.dedent("""
    import numpy as np, dem
    from dem import fused_steps
    g = np.stack(np.meshgrid(*[np.arange(5)] * 3, indexing="ij"), -1).reshape(-1, 3)
    p = dem.Particles.spheres((g + 0.5) * 2.0e-3, 1e-3, 2650.0)
    mat = dem.ContactMaterial(E=2.9e7, nu=0.25, density=2650.0, friction=0.5,
                              restitution=0.5)
    sim = dem.Simulation(p, mat, dem.box_walls((0, 0, 0), (0.01,) * 3), (0, 0, -9.81))
    sim.step(30)
    k = fused_steps._steps
    print(sum(k.stats.cache_misses.values()), sum(k.stats.cache_hits.values()))
""")


def test_fused_steps_load_from_the_disk_cache(tmp_path):
    """A second process loads the fused loop from numba's disk cache (no compilation)."""
    script = tmp_path / "run.py"
    script.write_text(CACHE_SCRIPT)
    env = dict(os.environ, PYTHONPATH=os.getcwd(), NUMBA_NUM_THREADS="1")
    for _ in range(2):
        out = subprocess.run([sys.executable, str(script)], env=env, check=True,
                             capture_output=True, text=True, cwd=os.getcwd())
    misses, hits = (int(a) for a in out.stdout.split())
    assert misses == 0 and hits >= 1


def test_a_subclass_that_changes_the_loop_keeps_the_python_loop(monkeypatch):
    calls = counted(monkeypatch)

    class Booked(dem.Simulation):
        def _book(self, *args):
            self.booked = getattr(self, "booked", 0) + 1
            super()._book(*args)

    sim = scene(3)
    sim.__class__ = Booked
    sim.step(20)
    assert sim.booked == 20 and not calls
    sim.__class__ = dem.Simulation
    sim.step(5)
    assert calls
