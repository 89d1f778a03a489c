"""dem.parallel: `DistributedSimulation.from_simulation` continues a serial `dem.Simulation`.

The scene: 527 frictional Hertz-Mindlin spheres (radii 1-1.01 mm) on a touching fcc lattice,
so slightly overlapping: they push apart into a dense agitated packing in a box whose -x
side moves in, under gravity, with a constant pull on a few grains and a GHOST clump (a
column of spheres with a tip) above them. It runs serially for a while (tangential springs
loaded at ~1700 contacts), then the clump is pushed down by `dem.Translated` (by global id =
serial row) for 200 steps by the serial run and by the distributed run converted from it.

Tolerances: on one rank the distributed run *is* the serial one continued (the same
operations on the same bits: arrays in serial-row order, forces, force parts, history and
walls carried as stored), so the comparison is exact. On more ranks every owned particle
sees its contacts in the serial order from the same data (`dem.parallel`), so the particles
agree bit for bit too (measured: 0.0); the bound 1e-12 x the largest value, as in
test_dem_parallel.py, still fails on any lost contact history or changed summation order in
this chaotic packing, which amplifies a round-off difference by orders of magnitude within a
hundred steps. The walls' forces are the ranks' shares added in rank order, another order
than the serial pass's: round-off of a sum of a few hundred contacts (1e-12 of the largest,
measured ~1e-16), not fed back (the walls move at a set velocity). The energy ledger: sums in
another order over ranks, 1e-10 of the energy scale as in test_dem_parallel.py.
"""

import hashlib

import numpy as np
import pytest

import dem
from dem.packing import lattice_packing
from dem.parallel import DistributedSimulation
from dem.parallel.simulation import _differs_across_ranks

R, RHO, SETTLE, PUSH = 1.0e-3, 2650.0, 400, 200


def scene(seed=5):
    """Particles, material, walls, the pulled rows and the clump's rows."""
    rng = np.random.default_rng(seed)
    x, r = lattice_packing((0, 0, 0), (20 * R, 14 * R, 14 * R), R, kind="fcc")
    r = r * rng.uniform(1.0, 1.01, len(r))
    top = (x[:, 2] + r).max()
    zc = top + 0.9 * R + np.arange(5) * 0.8 * R
    # tilted across the default cut (x = 9.5 R on two ranks): the clump is on both ranks
    pen = np.column_stack([(9.8 - 0.12 * np.arange(5)) * R, np.full(5, 6.7 * R), zc])
    pen = np.vstack([pen, pen[:1] - [0.0, 0.0, 0.6 * R]])
    kind = np.r_[np.zeros(len(x)), np.full(len(pen), dem.GHOST)].astype(np.int8)
    p = dem.Particles.spheres(np.vstack([x, pen]), np.r_[r, np.full(5, 0.8 * R), 0.3 * R], RHO,
                              kind=kind)
    mat = dem.ContactMaterial(E=2.9e7, nu=0.25, density=RHO, friction=0.5, restitution=0.5)
    lo, hi = x.min(axis=0) - R, x.max(axis=0) + [R, R, 4 * R]
    walls = dem.box_walls(lo, hi)
    walls[0] = dem.PlaneWall(tuple(lo), (1, 0, 0), velocity=(0.02, 0.0, 0.0))  # moves in
    return p, mat, walls, np.arange(0, len(x), 50), np.arange(len(x), p.n)


def settled(prescribed_pairs=True):
    """The serial run after SETTLE steps (a pull [N] on some grains, the last 100 damped),
    and the clump's rows."""
    p, mat, walls, pulled, pen = scene()
    sim = dem.Simulation(p, mat, walls, (0, 0, -9.81), allow_overlap=True,
                         prescribed_pairs=prescribed_pairs)
    sim.set_external_force(pulled, (1e-4, 0.0, 5e-4))
    sim.step(SETTLE - 100)
    sim.step(100, decay=0.995)  # (damping_removed carries on)
    return sim, pen


def push(run, pen, base):
    """The clump pushed down at 1.5 m/s from ``base`` for PUSH steps, in two calls."""
    depth = 0.0
    for n in (PUSH // 2, PUSH - PUSH // 2):
        cone = dem.Translated(pen, base, (0.0, 0.0, 1.0), offset=-depth, speed=-1.5)
        run.step(n, prescribed=dem.Prescribed(cone))
        depth = -float(cone.offsets(n, run.dt)[-1])


def checksum(sim) -> str:
    h = hashlib.sha256()
    for k, v in sorted(sim.state_dict().items()):
        h.update(k.encode() + np.ascontiguousarray(v).tobytes())
    return h.hexdigest()


def carried_history(dsim, sim):
    """The largest difference between the distributed run's contact history (of the pairs
    whose lower id, and the wall contacts whose particle, this rank owns) and the serial
    one's, the same of the forces on i by j of the touching pairs evaluated now, the count
    of those pairs with a history and of the touching ones (a pair the serial list does not
    hold has no history)."""
    s, g, n = dsim.local, dsim.gid, sim.p.n
    if s is None:  # (a rank the owners leave empty)
        return 0.0, 0.0, 0, 0
    nl, snl = s.nl, sim.nl
    err, live = 0.0, 0
    for i, j, names in ((nl.pi, g[nl.pj], ("hist", "slip", "etan")),
                        (nl.wi, nl.ww, ("whist", "wslip", "wetan"))):
        si, sj = (snl.pi, snl.pj) if names[0] == "hist" else (snl.wi, snl.ww)
        key = dict(zip((si * n + sj).tolist(), range(len(si)), strict=True))
        own = np.flatnonzero(dsim.owned[i])
        k = np.array([key.get(int(a), -1) for a in g[i[own]] * n + j[own]], np.int64)
        for name in names:
            mine, ref = getattr(nl, name)[own], getattr(snl, name)
            ref = np.where((k >= 0).reshape((-1,) + (1,) * (ref.ndim - 1)), ref[k], 0)
            err = max(err, float(np.abs(mine - ref).max(initial=0.0)))
        if names[0] == "hist":
            live = int((nl.hist[own] != 0).any(axis=1).sum())
    pairs, f = s.contact_forces(skip_ghost_pairs=False)
    pi, pj = pairs.T
    mine = dsim.owned[pi]
    pairs, sf = sim.contact_forces(skip_ghost_pairs=False)
    si, sj = pairs.T
    key = dict(zip((si * n + sj).tolist(), range(len(si)), strict=True))
    q = np.array([key[int(a)] for a in g[pi[mine]] * n + g[pj[mine]]], np.int64)
    ferr = float(np.abs(f[mine] - sf[q]).max(initial=0.0))
    return err, ferr, live, int(mine.sum())


def assert_continues(dsim, sim, pen, exact):
    comm = dsim.comm
    out, err = dsim.gather(), None
    if comm.rank == 0:
        err = {k: float(np.abs(out[k] - getattr(sim.p, k)).max()
                        / np.abs(getattr(sim.p, k)).max())
               for k in ("x", "v", "omega", "force", "torque")}
        err["walls"] = float(np.abs(dsim.wall_forces() - sim.walls.force).max()
                             / np.abs(sim.walls.force).max())
    else:
        dsim.wall_forces()  # (collective)
    err = comm.bcast(err, root=0)
    if exact:
        assert max(err.values()) == 0.0, err
    else:
        assert max(err.values()) <= 1e-12, err
    assert np.array_equal(dsim.walls.point, sim.walls.point)
    assert np.array_equal(dsim.values_of(pen, "x"), sim.p.x[pen])  # prescribed: exact
    fc = dsim.force_on(pen)
    assert np.abs(fc - sim.p.force[pen].sum(axis=0)).max() <= \
        (0.0 if exact else 1e-12) * np.abs(fc).max()
    assert (dsim.time, dsim.nsteps) == (sim.time, sim.nsteps)
    assert abs(dsim.damping_removed - sim.damping_removed) <= 1e-12 * sim.damping_removed
    en, es = dsim.energy(), sim.energy()
    scale = es["initial"] + abs(es["work_gravity"]) + abs(es["work_walls"]) \
        + abs(es["work_ghosts"])
    eerr = {k: abs(en[k] - es[k]) / scale for k in en}
    assert max(eerr.values()) <= 1e-10, eerr
    return err


@pytest.mark.mpi
@pytest.mark.parametrize("prescribed_pairs, cut", [(True, None), (False, None), (False, "z")])
def test_continues_the_serial_run(prescribed_pairs, cut):
    """The same serial run on every rank, converted after SETTLE steps and pushed: its
    contact history is carried (every non-zero entry, to the bit; the forces evaluated from
    it equal the serial ones), and positions, velocities, forces, the walls' forces, the
    clump's force and the energy ledger continue the serial run's (exactly on one rank).
    Cuts: the default bisection (across x, through the tilted clump), or the caller's
    slabs across z half a radius below the top grain (the clump above, its grains below)."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    sim, pen = settled(prescribed_pairs)
    owner = None
    if cut == "z":
        zcut = sim.p.x[: pen[0], 2].max() - 0.5 * R

        def owner(x):
            return np.where(x[:, 2] < zcut, comm.size - 1, 0).astype(np.int64)

    before = checksum(sim)
    dsim = DistributedSimulation.from_simulation(sim, comm, owner=owner)
    assert checksum(sim) == before  # the serial run is left as it was
    assert dsim.prescribed_pairs is prescribed_pairs and dsim.dt == sim.dt

    herr, ferr, live, touching = carried_history(dsim, sim)
    herr, ferr = comm.allreduce(herr, op=MPI.MAX), comm.allreduce(ferr, op=MPI.MAX)
    live, touching = comm.allreduce(live), comm.allreduce(touching)
    assert herr == 0.0 and ferr == 0.0
    assert live == int((sim.nl.hist != 0).any(axis=1).sum()) > 1000  # all of it, carried
    assert touching == len(sim.contact_forces(skip_ghost_pairs=False)[0])
    assert np.abs(sim.nl.hist[:, :3]).max() > 1e-7 * R  # the springs are loaded
    assert np.array_equal(dsim.wall_forces(), sim.walls.force)  # carried, not yet summed
    assert_continues(dsim, sim, pen, exact=True)  # at the conversion: nothing has run

    base = sim.p.x[pen].copy()
    push(sim, pen, base)
    push(dsim, pen, base)
    assert_continues(dsim, sim, pen, exact=comm.size == 1)
    assert abs(sim.p.force[pen, 2].sum()) > 0.1  # [N]: the clump is in the packing
    if comm.size > 1:
        assert comm.allreduce(int((~dsim.owned).any())) >= 2  # halos exist (z: a rank empty)
        out = dsim.gather()  # (collective)
        rank = comm.bcast(None if out is None else out["rank"])
        i, j = sim.contacts()
        grain = np.isin(i, pen) != np.isin(j, pen)
        assert (rank[i[grain]] != rank[j[grain]]).any()  # the clump meets other ranks' grains
        if cut is None and comm.size == 2:  # (the clump is tilted across this cut)
            assert len(np.unique(rank[pen])) > 1  # and its spheres are on both sides


@pytest.mark.mpi
def test_different_serial_states_are_named():
    """A serial run that differs on some rank is refused on every rank, naming the checksum
    (on one rank: the check against a stand-in for a second rank)."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    sim, _ = settled()
    if comm.size == 1:
        class TwoRanks:
            def allgather(self, x):
                return [x, dict(x, **{"particles.v": "0"})]

        err = _differs_across_ranks(TwoRanks(), sim)
        assert isinstance(err, ValueError)
        assert "ranks [1] differ from rank 0 in ['particles.v']" in str(err)
        assert _differs_across_ranks(comm, sim) is None
        return
    if comm.rank == comm.size - 1:
        sim.p.v[3, 0] = np.nextafter(sim.p.v[3, 0], np.inf)  # one bit
    with pytest.raises(ValueError, match=rf"ranks \[{comm.size - 1}\] differ from rank 0 in "
                       r"\['particles.v'\]"):
        DistributedSimulation.from_simulation(sim, comm)


def test_refuses_what_it_cannot_continue():
    from mpi4py import MPI

    sim, _ = settled()
    d = DistributedSimulation.from_simulation(sim, MPI.COMM_SELF)
    with pytest.raises(ValueError, match="must be a dem.Simulation"):
        DistributedSimulation.from_simulation(d, MPI.COMM_SELF)
    with pytest.raises(ValueError, match="must be a dem.Simulation"):
        DistributedSimulation.from_simulation(d.local, MPI.COMM_SELF)
    with pytest.raises(ValueError, match="halo_skin"):
        DistributedSimulation.from_simulation(sim, MPI.COMM_SELF, halo_skin=0.0)


@pytest.mark.mpi
def test_constructor_forwards_prescribed_pairs():
    """``DistributedSimulation(..., prescribed_pairs=False)`` from particles on rank 0 skips
    the contacts of two prescribed particles as the serial run does (judged on the
    particles' own kinds: a halo copy of a FREE grain is GHOST in its local run), the clump
    pushed into the grains: the same particles and clump force."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    p, mat, walls, _, pen = scene()
    copy = dem.Particles.from_state_dict(p.state_dict())
    sim = dem.Simulation(copy, mat, walls, (0, 0, -9.81), allow_overlap=True,
                         prescribed_pairs=False)
    dsim = DistributedSimulation(p if comm.rank == 0 else None, mat, walls, (0, 0, -9.81),
                                 comm=comm, allow_overlap=True, prescribed_pairs=False)
    assert dsim.local.prescribed_pairs is False
    nl, kind = dsim.local.nl, dsim._kinds[dsim.gid]
    assert ((kind[nl.pi] == dem.FREE) | (kind[nl.pj] == dem.FREE)).all()
    base = sim.p.x[pen].copy()
    push(sim, pen, base)
    push(dsim, pen, base)
    assert_continues(dsim, sim, pen, exact=comm.size == 1)
    assert abs(sim.p.force[pen, 2].sum()) > 0.1  # [N]: the clump is in the packing


@pytest.mark.mpi
def test_a_restart_continues_bit_for_bit():
    """A converted run's `state_dict` (one per rank), loaded into another conversion of the
    same serial run (a coupled run's restart), continues as the first one does, to the bit."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    sim, pen = settled(False)
    base = sim.p.x[pen].copy()
    first = DistributedSimulation.from_simulation(sim, comm, prescribed_pairs=False)
    cone = dem.Translated(pen, base, (0.0, 0.0, 1.0), speed=-1.5)
    first.step(PUSH // 2, prescribed=dem.Prescribed(cone))
    state = first.state_dict()
    again = DistributedSimulation.from_simulation(sim, comm, prescribed_pairs=False)
    again.load_state(state)
    for run in (first, again):
        depth = -float(cone.offsets(PUSH // 2, run.dt)[-1])
        run.step(PUSH // 2, prescribed=dem.Prescribed(dem.Translated(
            pen, base, (0.0, 0.0, 1.0), offset=-depth, speed=-1.5)))
    a, b = first.gather(), again.gather()
    differ = comm.bcast(None if a is None else [k for k in a if not np.array_equal(a[k], b[k])])
    assert differ == [], differ
    assert np.array_equal(first.wall_forces(), again.wall_forces())
    assert first.energy() == again.energy()


@pytest.mark.mpi
def test_an_empty_rank_takes_particles_at_a_decomposition():
    """All particles on rank 0 at the conversion (the others empty), then owners by slabs
    across x from a decomposition on: the empty ranks receive particles and history, and the
    run still continues the serial one."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    sim, pen = settled(False)
    slabs = [False]

    def owner(x):
        if not slabs[0]:
            return np.zeros(len(x), np.int64)
        return np.minimum((x[:, 0] / (20 * R) * comm.size).astype(np.int64), comm.size - 1)

    dsim = DistributedSimulation.from_simulation(sim, comm, owner=owner)
    assert comm.allreduce(int(dsim.local is None)) == comm.size - 1
    slabs[0] = True
    dsim._decompose()
    assert dsim.local is not None
    base = sim.p.x[pen].copy()
    push(sim, pen, base)
    push(dsim, pen, base)
    assert_continues(dsim, sim, pen, exact=comm.size == 1)


@pytest.mark.mpi
def test_force_sums_are_the_serial_ones():
    """``step(sums=...)``: the forces on the clump's spheres and some grains summed over the
    push by each rank's local loop (the rows it owns), added over the ranks, are the serial
    run's sums (its fused loop) to round-off, through the push's decompositions; a misfit
    buffer is refused, named."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    sim, pen = settled()
    dsim = DistributedSimulation.from_simulation(sim, comm)
    rows = np.r_[pen, np.arange(0, pen[0], 37)].astype(np.int64)
    out, ref = np.zeros((len(rows), 3)), np.zeros((len(rows), 3))
    base = sim.p.x[pen].copy()
    cone = dem.Translated(pen, base, (0.0, 0.0, 1.0), offset=0.0, speed=-1.5)
    sim.step(PUSH, prescribed=dem.Prescribed(cone), sums=(rows, ref))
    dsim.step(PUSH, prescribed=dem.Prescribed(cone), sums=(rows, out))
    total = comm.allreduce(out)
    assert np.abs(ref).max() > 0 and (comm.size == 1 or dsim.decompositions > 1)
    assert np.abs(total - ref).max() <= 1e-12 * np.abs(ref).max()
    with pytest.raises(ValueError, match="sums: out must have shape"):
        dsim.step(1, sums=(rows, np.zeros((len(rows), 2))))
