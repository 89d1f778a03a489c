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
from dem.packing import lattice_packing
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
    assert max(err.values()) <= tol, err
    en, es = dsim.energy(), sim.energy()
    assert en.keys() == es.keys()
    # the ledger's sums run in another order over the ranks: round-off of the energy scale
    scale = es["initial"] + abs(es["work_gravity"]) + abs(es["work_walls"])
    err = {k: abs(en[k] - es[k]) / scale for k in en}
    assert max(err.values()) <= 1e-10, err


@pytest.mark.mpi
def test_matches_serial_with_migration():
    """Recursive bisection cutting across z (the grains fall through the cut): same x, v,
    omega, forces, torques and energy ledger as the serial run."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    p, mat, walls, sim = serial_reference()
    across_z = RecursiveBisection.from_points(p.x, comm.size, axes=(2,))
    dsim = DistributedSimulation(p if comm.rank == 0 else None, mat, walls, (0, 0, -9.81),
                                 comm=comm, owner=across_z, halo_skin=0.2 * R)  # (= skin)
    dsim.step(STEPS)
    assert_same_as_serial(dsim, sim)
    assert len(sim.contacts()[0]) > 100  # a real contact network ...
    assert np.abs(sim.p.omega).max() > 10.0  # ... with rotations
    if comm.size > 1:
        assert dsim.decompositions > 10  # history carried through many re-decompositions
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


@pytest.mark.mpi
def test_external_forces_follow_their_particles_across_ranks():
    """`DistributedSimulation.set_external_force` by global id equals the serial run's
    `Simulation.set_external_force` on the same rows (a sideways and upward pull on a third of
    the grains while they fall through the cut, then replaced, then removed), the external
    work included in the ledger; bad ids are refused by name on every rank."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    p, mat, walls = settling_box()
    rows = np.arange(0, p.n, 3)
    pull = np.tile([2e-5, 0.0, 1e-4], (len(rows), 1))     # [N], of the order of the weights
    sim = dem.Simulation(copy(p), mat, walls, (0, 0, -9.81))
    across_z = RecursiveBisection.from_points(p.x, comm.size, axes=(2,))
    dsim = DistributedSimulation(p if comm.rank == 0 else None, mat, walls, (0, 0, -9.81),
                                 comm=comm, owner=across_z, halo_skin=0.2 * R)
    for run in (sim, dsim):
        run.step(50)
        run.set_external_force(rows, pull)
        run.step(100)
        run.set_external_force(rows[::2], -pull[::2])
        run.step(100)
        run.set_external_force(None, None)
        run.step(50)
    assert_same_as_serial(dsim, sim)
    assert abs(sim.energy()["work_external"]) > 1e-3 * sim.energy()["initial"]
    if comm.size > 1:
        assert dsim.decompositions > 5 and dsim.migrated > 0
    with pytest.raises(ValueError, match="gids must lie in"):
        dsim.set_external_force([p.n], (0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="gids repeat"):
        dsim.set_external_force([1, 1], (0.0, 0.0, 1.0))


def test_one_rank_equals_simulation_exactly():
    """On one rank the run is the plain `Simulation` bit for bit and never decomposes
    again (no halo to go stale); decompositions forced between calls rebuild the local
    run, carrying forces and history by global id, and change no bit either, nor the
    ledger beyond round-off."""
    from mpi4py import MPI

    p, mat, walls, sim = serial_reference()
    dsim = DistributedSimulation(copy(p), mat, walls, (0, 0, -9.81), comm=MPI.COMM_SELF)
    dsim.step(STEPS // 2)
    assert dsim.decompositions == 1
    dsim._unchanged = lambda: False  # (else a decomposition sees nothing to change)
    for _ in range(10):
        dsim._decompose()
        dsim.step(STEPS // 20)
    out = dsim.gather()
    for k in ("x", "v", "omega", "force", "torque"):
        assert np.array_equal(out[k], getattr(sim.p, k)), k
    assert np.array_equal(dsim.walls.point, sim.walls.point)
    en, es = dsim.energy(), sim.energy()
    assert max(abs(en[k] - es[k]) for k in en) <= 1e-12 * es["initial"]


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


@pytest.mark.mpi
def test_halo_skin_below_a_step_is_named():
    """A halo that one step outruns is an error on every rank (one rank has no halo)."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    p, mat, walls = settling_box(2, 2, 2)
    d = DistributedSimulation(p if comm.rank == 0 else None, mat, walls, (0, 0, -9.81),
                              comm=comm, halo_skin=1e-9)
    if comm.size == 1:
        d.step(5)
        return
    with pytest.raises(dem.TimeStepError, match="halo_skin"):
        d.step(5)


@pytest.mark.mpi
def test_energy_ledger_matches_serial_and_closes():
    """A dissipative settle (damping, friction, gravity, spin) onto a floor that slides and
    rises, cut along g by default so that halo copies touch the floor too: every key of the
    distributed ledger equals the serial run's to round-off of the energy scale at every
    sample, and so it closes as the serial one does (to the time error of the Hertz normal
    forces)."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    p, mat, walls = settling_box()
    walls[4] = dem.PlaneWall((0, 0, 0), (0, 0, 1), velocity=(0.2, 0.0, 0.02))  # the floor
    sim = dem.Simulation(copy(p), mat, walls, (0, 0, -9.81))
    dsim = DistributedSimulation(p if comm.rank == 0 else None, mat, walls, (0, 0, -9.81),
                                 comm=comm)
    for _ in range(4):
        sim.step(75)
        dsim.step(75)
        en, es = dsim.energy(), sim.energy()
        assert en.keys() == es.keys()
        scale = es["initial"] + abs(es["work_gravity"]) + abs(es["work_walls"])
        err = {k: abs(en[k] - es[k]) / scale for k in en}
        assert max(err.values()) <= 1e-10, err
    assert es["dissipated_damping"] > 0.05 * scale and es["dissipated_friction"] > 0.0
    assert es["work_walls"] != 0.0 and es["elastic"] > 0.0
    # what is left is the serial run's time error (0.3 % of the energy scale at this dt)
    assert abs(en["balance"]) < 0.01 * (es["dissipated_damping"] + es["dissipated_friction"])
    if comm.size > 1:
        assert dsim.decompositions > 3
        assert comm.allreduce(int((~dsim.owned).sum()), op=MPI.MIN) > 0  # halos exist


def test_blowup_writes_the_last_good_state(tmp_path):
    """A corrupted state raises BlowUpError at the next check, with the state of the check
    before written (global ids, x, v, omega), as `Simulation` does."""
    from mpi4py import MPI

    p, mat, walls = settling_box(2, 2, 2)
    path = str(tmp_path / "last.npz")
    d = DistributedSimulation(copy(p), mat, walls, (0, 0, -9.81), comm=MPI.COMM_SELF,
                              check_every=5, state_path=path)
    d.step(5)
    d.local.p.v[3] = (300.0, 0.0, 0.0)  # a kinetic energy from nowhere
    with pytest.raises(dem.BlowUpError, match="kinetic energy jump") as err:
        d.step(5)
    good = np.load(err.value.path)
    assert int(good["step"]) == 5 and np.isfinite(good["v"]).all()
    assert np.array_equal(good["gid"], np.arange(p.n)) and good["x"].shape == (p.n, 3)


# ---------------------------------------------------------------- calibration chamber
def chamber():
    """A cone-penetration chamber in miniature: 295 spheres on an fcc lattice in a box of
    smooth side walls (material 1: the grains' material without friction) on a rough
    floor, and a GHOST clump (a column of overlapping spheres with a small tip sphere) 0.1
    R above them, off the axis. Returns particles, materials, walls, the clump's rows, the
    top grains' rows."""
    from dataclasses import replace

    x, r = lattice_packing((0, 0, 0), (12 * R, 12 * R, 14 * R), R, kind="fcc")
    top = (x[:, 2] + r).max()
    zc = top + 0.9 * R + np.arange(6) * 0.8 * R
    pen = np.column_stack([np.full(6, 6.3 * R), np.full(6, 5.8 * R), zc])
    pen = np.vstack([pen, pen[:1] - [0.0, 0.0, 0.6 * R]])
    kind = np.r_[np.zeros(len(x)), np.full(len(pen), dem.GHOST)].astype(np.int8)
    p = dem.Particles.spheres(np.vstack([x, pen]), np.r_[r, np.full(6, 0.8 * R), 0.3 * R], RHO,
                              kind=kind)
    mat = dem.ContactMaterial(E=2.9e7, nu=0.25, density=RHO, friction=0.5, restitution=0.5)
    walls = dem.box_walls(x.min(axis=0) - R, x.max(axis=0) + R, material=1)
    walls[4] = dem.PlaneWall(tuple(x.min(axis=0) - R), (0, 0, 1))  # the floor: rough
    return p, [mat, replace(mat, friction=0.0)], walls, np.arange(len(x), p.n), \
        np.flatnonzero(x[:, 2] > x[:, 2].max() - R)


def consolidate_and_push(run, p, pen, surcharged, blocks=8, substeps=50):
    """What the penetration's full-DEM reference does to a run (`Simulation` or
    `DistributedSimulation`), through the calls they share: a surcharge on the top grains,
    free then damped steps, `dem.relax`, then the clump lowered 0.05 R (a jump, as
    `lower_penetrator` moves it) and pushed down in blocks by `Translated` (as
    `coupling.substep.sub_cycle`). Returns relax's record and the clump's force (3,) after
    each block."""
    run.set_external_force(surcharged, (0.0, 0.0, -20.0 * p.mass[0] * 9.81))
    run.step(100)
    assert run.step(150, decay=0.97) == 150
    info = dem.relax(run, tol=0.02, max_steps=3000)
    base = p.x[pen] - [0.0, 0.0, 0.05 * R]
    depth, forces = 0.0, []
    for _ in range(blocks):
        cone = dem.Translated(pen, base, (0.0, 0.0, 1.0), offset=-depth, speed=-1.5)
        run.step(substeps, prescribed=dem.Prescribed(cone))
        depth = -float(cone.offsets(substeps, run.dt)[-1])
        forces.append(run.force_on(pen) if isinstance(run, DistributedSimulation)
                      else run.p.force[pen].sum(axis=0))
    return info, np.array(forces)


@pytest.mark.mpi
def test_prescribed_clump_decay_and_relax_match_serial():
    """The calibration chamber's calls on two ranks equal the serial run: `step` with
    ``decay`` (and `damping_removed`), `dem.relax` (its steps, ratio and energy removed)
    and the GHOST clump pushed by `Translated` through ``step(prescribed=...)`` by global
    id, crossing the cut between the ranks (it migrates; each rank writes its owned and
    halo copies) after a jump; smooth walls of a second material. Positions of every
    particle, the clump's force, the energy ledger: to round-off."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    p, mats, walls, pen, surcharged = chamber()
    zcut = p.x[surcharged, 2].min() - 0.5 * R  # the clump's tip crosses it in the push

    def slabs(x):
        return np.where(x[:, 2] < zcut, comm.size - 1, 0).astype(np.int64)

    sim = dem.Simulation(copy(p), mats, walls, (0, 0, -9.81), allow_overlap=True)
    dsim = DistributedSimulation(p if comm.rank == 0 else None, mats, walls, (0, 0, -9.81),
                                 comm=comm, owner=slabs, halo_skin=0.2 * R, allow_overlap=True)
    owner0 = dsim.gather()
    serial = consolidate_and_push(sim, p, pen, surcharged)
    dist = consolidate_and_push(dsim, p, pen, surcharged)
    assert dist[0]["steps"] == serial[0]["steps"] > 200
    for k in ("ratio", "energy_removed"):
        assert abs(dist[0][k] - serial[0][k]) <= 1e-10 * abs(serial[0][k]), k
    assert abs(dsim.damping_removed - sim.damping_removed) <= 1e-10 * sim.damping_removed
    assert np.abs(dist[1] - serial[1]).max() <= 1e-10 * np.abs(serial[1]).max()
    assert np.abs(serial[1][-1, 2]) > 10 * np.abs(serial[1][0, 2])  # the tip met the grains
    assert np.array_equal(dsim.values_of(pen, "x"), sim.p.x[pen])  # prescribed: exact
    assert_same_as_serial(dsim, sim)
    out = dsim.gather()
    if comm.size > 1:
        assert dsim.decompositions > 5
        moved = comm.bcast(None if out is None else
                           int((out["rank"][pen] != owner0["rank"][pen]).sum()))
        assert moved > 0  # clump spheres changed rank in the push


def test_distributed_step_refuses_what_it_cannot_do():
    """A prescribed motion of a FREE particle and unknown ids are named."""
    from mpi4py import MPI

    p, mats, walls, pen, _ = chamber()
    d = DistributedSimulation(p, mats, walls, comm=MPI.COMM_SELF, allow_overlap=True)
    with pytest.raises(ValueError, match="not GHOST"):
        d.step(1, prescribed=dem.Prescribed(dem.Translated([0], p.x[:1], (0, 0, 1))))
    with pytest.raises(ValueError, match="gids must lie in"):
        d.values_of([p.n])
