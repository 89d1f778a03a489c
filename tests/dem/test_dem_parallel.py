"""dem.parallel: spatial decomposition over MPI ranks equals the serial `Simulation`.

The tolerance: the decomposition keeps the local arrays in global-id order and gives every
owned particle all its contacts, so its forces are summed in the serial order from the same
data, and the runs agree bit for bit (measured: 0.0). A dense frictional packing amplifies
any round-off difference by orders of magnitude within a few hundred steps, so a bound of
1e-12 x the largest value still fails on any change of summation order or of contact
history, while allowing a compiler that contracts a multiply-add differently in a kernel.
"""

import numpy as np
import pytest

import dem
from dem.parallel import DistributedSimulation, RecursiveBisection

R, RHO, STEPS = 1.0e-3, 2650.0, 300


def settling_box(nx=6, ny=6, nz=12, seed=3):
    """432 spheres (radii 0.9-1 mm) on a jittered lattice in a closed box, thrown down at
    ~0.5 m/s with random velocities and spins: Hertz-Mindlin, friction 0.5, e = 0.5."""
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"),
                 -1).reshape(-1, 3)
    s = 2.1 * R
    x = (g + 0.5) * s + rng.uniform(-0.02 * R, 0.02 * R, g.shape)
    v = rng.normal(0.0, 0.4, x.shape) - [0.0, 0.0, 0.5]
    p = dem.Particles.spheres(x, R * rng.uniform(0.9, 1.0, len(x)), RHO, v=v,
                              omega=rng.normal(0.0, 200.0, x.shape))
    mat = dem.ContactMaterial(E=2.9e7, nu=0.25, density=RHO, friction=0.5, restitution=0.5)
    walls = dem.box_walls((0, 0, 0), (nx * s, ny * s, nz * s + 10 * R), top=True)
    return p, mat, walls


def copy(p):
    return dem.Particles.from_state_dict(p.state_dict())


def serial_reference(steps=STEPS):
    p, mat, walls = settling_box()
    sim = dem.Simulation(copy(p), mat, walls, (0, 0, -9.81))
    sim.step(steps)
    return p, mat, walls, sim


def assert_same_as_serial(dsim, sim, tol=1e-12):
    """Relative differences computed on rank 0, broadcast, then asserted on every rank (a
    rank failing alone would leave the others in a collective call)."""
    out, err = dsim.gather(), None
    if dsim.comm.rank == 0:
        err = {k: np.abs(out[k] - getattr(sim.p, k)).max() / np.abs(getattr(sim.p, k)).max()
               for k in ("x", "v", "omega", "force", "torque")}
    err = dsim.comm.bcast(err, root=0)
    en, es = dsim.energy(), sim.energy()
    err.update({k: abs(en[k] - es[k]) / abs(es[k]) for k in en})
    assert max(err.values()) <= tol, err


@pytest.mark.mpi
def test_matches_serial_with_migration():
    """Recursive bisection (cut across z: the grains fall through it): same x, v, omega,
    forces, torques, kinetic energy and work of gravity as the serial run."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    p, mat, walls, sim = serial_reference()
    dsim = DistributedSimulation(p if comm.rank == 0 else None, mat, walls, (0, 0, -9.81),
                                 comm=comm)
    dsim.step(STEPS)
    assert_same_as_serial(dsim, sim)
    assert len(sim.contacts()[0]) > 100  # a real contact network ...
    assert np.abs(sim.p.omega).max() > 10.0  # ... with rotations
    assert dsim.decompositions > 10  # history carried through many re-decompositions
    if comm.size > 1:
        assert dsim.migrated > 0
        assert comm.allreduce(int((~dsim.owned).sum()), op=MPI.MIN) > 0  # halos exist


@pytest.mark.mpi
def test_caller_ownership_matches_serial():
    """A caller's owner function (slabs across x, ranks in reverse order) gives the same
    run: the coupling can make particles follow an FE partition."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    p, mat, walls, sim = serial_reference(150)
    lx = 6 * 2.1 * R

    def slabs(x):
        k = np.clip((x[:, 0] / lx * comm.size).astype(np.int64), 0, comm.size - 1)
        return comm.size - 1 - k

    dsim = DistributedSimulation(p if comm.rank == 0 else None, mat, walls, (0, 0, -9.81),
                                 comm=comm, owner=slabs, halo_skin=4e-4)
    dsim.step(150)
    assert_same_as_serial(dsim, sim)
    out = dsim.gather()
    follow = comm.bcast(None if out is None else (out["rank"] == slabs(out["x"])).mean())
    assert follow > 0.9  # owners follow the slabs


def test_one_rank_equals_simulation_exactly():
    """On one rank the run is the plain `Simulation` bit for bit, through decompositions
    that rebuild the local run and carry forces and history by global id."""
    from mpi4py import MPI

    p, mat, walls, sim = serial_reference()
    dsim = DistributedSimulation(copy(p), mat, walls, (0, 0, -9.81), comm=MPI.COMM_SELF)
    dsim.step(STEPS)
    out = dsim.gather()
    assert dsim.decompositions > 10
    for k in ("x", "v", "omega", "force", "torque"):
        assert np.array_equal(out[k], getattr(sim.p, k)), k
    assert np.array_equal(dsim.walls.point, sim.walls.point)


@pytest.mark.parametrize("nranks", [1, 2, 3, 5])
def test_recursive_bisection_balances_and_cuts_longest_axis(nranks):
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 1, (1000, 3)) * [1.0, 3.0, 0.5]  # longest axis: y
    rcb = RecursiveBisection.from_points(x, nranks)
    owner = rcb(x)
    counts = np.bincount(owner, minlength=nranks)
    assert counts.sum() == 1000 and len(counts) == nranks
    assert counts.max() - counts.min() <= 1
    if nranks > 1:
        assert rcb.axis[0] == 1
        assert np.array_equal(rcb(x[::-1]), owner[::-1])  # a function of position only


def test_errors_are_named():
    from mpi4py import MPI

    p, mat, walls = settling_box(2, 2, 2)
    with pytest.raises(ValueError, match="owner"):
        DistributedSimulation(copy(p), mat, walls, comm=MPI.COMM_SELF,
                              owner=lambda x: np.zeros(len(x) + 1, int))
    with pytest.raises(ValueError, match="particles must be"):
        DistributedSimulation(None, mat, walls, comm=MPI.COMM_SELF)
    with pytest.raises(ValueError, match="halo_skin"):
        DistributedSimulation(copy(p), mat, walls, comm=MPI.COMM_SELF, halo_skin=0.0)
    d = DistributedSimulation(copy(p), mat, walls, (0, 0, -9.81), comm=MPI.COMM_SELF,
                              halo_skin=1e-9)
    with pytest.raises(dem.TimeStepError, match="halo_skin"):
        d.step(5)
