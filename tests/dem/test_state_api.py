"""`Simulation.state_dict` / `load_state` (and `DistributedSimulation`'s): a run continued
from a saved state equals the run that went on, bit for bit (positions, velocities, spins
and the energy ledger); a state that does not fit is refused naming its key.

Exactness is the right tolerance: the continued run executes the same operations on the
same data; a frictional packing amplifies any lost bit (a contact history, a neighbour
list's build positions, a force part of the last step) far beyond round-off within a few
hundred steps.
"""

import numpy as np
import pytest
from test_dem_parallel import settling_box  # (tests/dem is on sys.path under pytest)
from test_prescribed import scene

import dem
from dem.prescribed import Prescribed, Translated


def box_of_eight():
    """8 Hertz-Mindlin spheres in a box whose lid moves down: walls with history."""
    mat = dem.ContactMaterial(E=2.9e8, nu=0.25, density=2650.0, friction=0.5, restitution=0.5)
    rng = np.random.default_rng(4)
    g = np.stack(np.meshgrid(*[np.arange(2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    L = 5e-3
    x = (g + 0.5) * (L / 2) + rng.uniform(-1e-4, 1e-4, (8, 3))
    p = dem.Particles.spheres(x, 1e-3, 2650.0, v=rng.normal(0, 1.0, (8, 3)),
                              omega=rng.normal(0, 300.0, (8, 3)))
    sim = dem.Simulation(p, mat, dem.box_walls((0, 0, 0), (L, L, L), top=True), (0, 0, -9.81))
    sim.walls.velocity[-1] = (0.0, 0.0, -0.05)
    return sim


def sheared_cell():
    """A periodic cell of 2D disks under simple shear (Lees-Edwards)."""
    R = 1e-3
    rng = np.random.default_rng(2)
    n = 8
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    x = np.column_stack([((i + 0.5 * (j % 2)) * 2 * R).ravel(),
                         (j * np.sqrt(3) * R).ravel()]) + 1e-5
    h = np.diag([n * 2 * R, n * np.sqrt(3) * R])
    p = dem.Particles.spheres(x, R * (1 - 0.05 * rng.random(n * n)), 2650.0, dim=2)
    mat = dem.ContactMaterial(E=2e5, nu=0.25, law="linear", kn=2e5, kt=1e5, density=2650.0,
                              friction=0.3, restitution=0.5)
    cell = dem.PeriodicCell(h, velocity_gradient=[[0.0, 40.0], [0.0, 0.0]])
    return dem.Simulation(p, mat, cell=cell, allow_overlap=True)


def prescribed_scene():
    return scene()[0]


def push(sim, n):
    """The scene's cone pushed down inside the step loop (prescribed rows)."""
    rows = np.flatnonzero(sim.p.kind == dem.GHOST)[-5:]
    base = np.zeros((5, 3))
    base[:, 0] = np.linspace(8e-3, 12e-3, 5)
    base[:, 1] = 8 * np.sqrt(3) * 1e-3 + 3e-3
    sim.step(n, prescribed=Prescribed(Translated(rows, base, (0, -1, 0), offset=sim.time * 0.5,
                                                 speed=0.5)))


CASES = {"ghosts_walls_prescribed": (prescribed_scene, push),
         "hertz_moving_lid": (box_of_eight, lambda s, n: s.step(n)),
         "periodic_shear": (sheared_cell, lambda s, n: s.step(n)),
         "settling_box": (lambda: dem.Simulation(*settling_box(), (0, 0, -9.81)),
                          lambda s, n: s.step(n))}


def assert_same(a, b):
    for key in ("x", "v", "omega", "force", "torque"):
        np.testing.assert_array_equal(getattr(a.p, key), getattr(b.p, key), err_msg=key)
    assert a.energy() == b.energy()
    assert a.ledger() == b.ledger()
    assert (a.time, a.nsteps, a.nl.builds) == (b.time, b.nsteps, b.nl.builds)


@pytest.mark.parametrize("case", CASES)
def test_round_trip_continues_bit_for_bit(case, tmp_path):
    """Run N steps, save (through an .npz file), run M -> the reference; a fresh Simulation
    built the same way loads the state and runs M: the same bits."""
    make, advance = CASES[case]
    a = make()
    advance(a, 230)
    np.savez(tmp_path / "state.npz", **a.state_dict())
    advance(a, 270)
    b = make()
    b.load_state(np.load(tmp_path / "state.npz"))
    assert b.nsteps == 230
    advance(b, 270)
    assert_same(a, b)
    assert a.nl.builds > 2  # the lists rebuilt after the restart: build positions mattered


def test_state_is_a_copy():
    sim = box_of_eight()
    d = sim.state_dict()
    x = d["particles.x"].copy()
    sim.step(10)
    np.testing.assert_array_equal(d["particles.x"], x)
    assert all(isinstance(v, (np.ndarray, int, float, bool)) for v in d.values())


def test_mismatched_state_is_refused_naming_the_key():
    small, big = box_of_eight(), dem.Simulation(*settling_box()[:3], (0, 0, -9.81))
    with pytest.raises(ValueError, match="'particles.x'"):
        small.load_state(big.state_dict())
    d = small.state_dict()
    del d["contacts.hist"]
    with pytest.raises(ValueError, match="'contacts.hist'"):
        box_of_eight().load_state(d)
    d = prescribed_scene().state_dict()
    assert len(d["contacts.slip"]) > 100
    d["contacts.slip"] = d["contacts.slip"][:-1]
    with pytest.raises(ValueError, match="'contacts.slip'"):
        prescribed_scene().load_state(d)
    with pytest.raises(ValueError, match="'cell."):  # a periodic state into a walled run
        prescribed_scene().load_state(sheared_cell().state_dict())


@pytest.mark.mpi
def test_distributed_round_trip(tmp_path):
    """DistributedSimulation over the ranks: run, save each rank's state, run on -> the
    reference; a fresh one built the same way loads the states and runs on: the same bits
    (gathered x, v, omega) and the same ledger."""
    from mpi4py import MPI

    from dem.parallel import DistributedSimulation

    comm = MPI.COMM_WORLD
    p, mat, walls = settling_box()

    def make():
        return DistributedSimulation(p if comm.rank == 0 else None, mat, walls, (0, 0, -9.81),
                                     comm=comm, halo_skin=0.2e-3)

    a = make()
    a.step(150)
    path = comm.bcast(str(tmp_path), root=0) + f"/rank{comm.rank}.npz"
    np.savez(path, **a.state_dict())
    a.step(200)
    b = make()
    b.load_state(np.load(path))
    b.step(200)
    ga, gb = a.gather(), b.gather()
    same = None
    if comm.rank == 0:
        same = {k: bool(np.array_equal(ga[k], gb[k])) for k in ("x", "v", "omega", "force")}
    same = comm.bcast(same, root=0)
    assert all(same.values()), same
    assert a.energy() == b.energy()
    assert a.decompositions == b.decompositions
    if comm.size > 1:
        assert a.decompositions > 1  # migrations after the restart: the plan mattered
    # a state of another run (other particle count) is refused on every rank
    other = DistributedSimulation(settling_box(nx=4)[0] if comm.rank == 0 else None, mat, walls,
                                  (0, 0, -9.81), comm=comm)
    with pytest.raises(ValueError, match="'ngid'"):
        other.load_state(a.state_dict())
    comm.barrier()
