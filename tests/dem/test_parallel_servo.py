"""dem.parallel: walls a servo drives on a `DistributedSimulation` (the calibration chamber's
top plate) equal the serial `Simulation`'s.

The wall's force is summed over the ranks (`DistributedSimulation.wall_forces`) in another
order than the serial pair loop's, so the servo's speed, and then everything it moves,
differs from the serial run by round-off: measured 2e-16 relative over the first 400 steps
and 2e-12 of a grain radius in the plate's height after the relaxation (1500 steps; the
bounds, 1e-11 and 1e-9 R, leave room for a dense packing's amplification of round-off,
`tests/dem/test_dem_parallel.py`). On one rank the run is the local `Simulation`'s, bit
for bit.
"""

import numpy as np
import pytest

import dem
from dem.control import mean_force_ratio, wall_force
from dem.packing import lattice_packing
from dem.parallel import DistributedSimulation

R, RHO = 1.0e-3, 2650.0
TARGET = 2.0e3  # the plate's stress [Pa]: ~10x the grains' weight over the plate
DT = 5e-6  # [s], 0.1 of the Rayleigh step


def plated_box():
    """About 300 spheres of radius R (fcc, jittered) in a box of smooth walls (material 1) under a
    smooth top plate (wall 5, ``free_only``) touching the highest sphere, and a GHOST column
    of three spheres through the plate (the cone of the chamber: it must not push it).
    Returns particles, materials, walls, the plate's servo, the column's rows."""
    from dataclasses import replace

    x, r = lattice_packing((0, 0, 0), (10 * R, 10 * R, 12 * R), R, kind="fcc", gap=0.005,
                           jitter=1.0, seed=4)
    top = float((x[:, 2] + r).max())
    col = np.column_stack([np.full(3, 5.1 * R), np.full(3, 4.9 * R),
                           top + R * np.array([1.2, 2.6, 4.0])])
    kind = np.r_[np.zeros(len(x)), np.full(3, dem.GHOST)].astype(np.int8)
    p = dem.Particles.spheres(np.vstack([x, col]), np.r_[r, np.full(3, 0.8 * R)], RHO,
                              kind=kind)
    mat = dem.ContactMaterial(E=2.9e7, nu=0.25, density=RHO, friction=0.5, restitution=0.5)
    lo, hi = x.min(axis=0) - R, x.max(axis=0) + R
    walls = dem.box_walls(lo, hi, material=1)
    walls.append(dem.PlaneWall((0.0, 0.0, top), (0, 0, -1), material=1, free_only=True))
    area = float((hi[0] - lo[0]) * (hi[1] - lo[1]))
    # gain: the plate moves 2e-4 R a step at an error of the target's size
    servo = dem.ServoWall(5, TARGET, area, gain=2e-4 * R / (TARGET * DT), v_max=0.2)
    return p, [mat, replace(mat, friction=0.0)], walls, servo, np.arange(len(x), p.n)


def copy(p):
    return dem.Particles.from_state_dict(p.state_dict())


def runs(comm):
    p, mats, walls, servo, col = plated_box()
    sim = dem.Simulation(copy(p), mats, walls, (0, 0, -9.81), dt=DT, allow_overlap=True)
    dsim = DistributedSimulation(p if comm.rank == 0 else None, mats, walls, (0, 0, -9.81),
                                 dt=DT, comm=comm, allow_overlap=True)
    return sim, dsim, servo, col


def servo_steps(run, servo, blocks=4, n=100):
    """The servo acting after every force pass (`dem.relax`'s hook), n steps a call; the
    plate's vertical force [N] and height [m] after each call."""
    out = []
    servo(run)
    for _ in range(blocks):
        assert run.step(n, hook=lambda: servo(run)) == n
        out.append([wall_force(run, servo.wall)[2], run.walls.point[servo.wall, 2]])
    return np.array(out)


def test_one_rank_servo_and_mean_force_ratio_are_the_serial_bits():
    """On one rank `dem.relax` with the plate's servo and `mean_force_ratio` is the local
    `Simulation`'s run: the same steps, ratio, plate and particles, bit for bit."""
    from mpi4py import MPI

    sim, dsim, servo, _ = runs(MPI.COMM_SELF)
    assert mean_force_ratio(dsim) == mean_force_ratio(sim)
    a = dem.relax(sim, tol=0.05, controllers=[servo], ratio=mean_force_ratio)
    b = dem.relax(dsim, tol=0.05, controllers=[servo], ratio=mean_force_ratio)
    assert a == b and a["steps"] > 100
    assert np.array_equal(dsim.walls.point, sim.walls.point)
    assert np.array_equal(dsim.wall_forces(), sim.walls.force)
    assert np.array_equal(dsim.gather()["x"], sim.p.x)


@pytest.mark.mpi
def test_servo_plate_matches_serial_then_reaches_its_stress():
    """Two ranks (the default bisection cuts the plate in two): over the first 400 steps the
    plate's force and height and every particle equal the serial run's to round-off, the
    summed force has the same bits on every rank; `dem.relax` with the servo and
    `mean_force_ratio` then holds the target stress in as many steps as the serial run, the
    plate where the serial one is to round-off; the GHOST column never touches it."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    sim, dsim, servo, col = runs(comm)
    first = servo_steps(sim, servo), servo_steps(dsim, servo)
    if comm.size > 1:  # two ranks (at least) carry a share of the plate
        share = 0.0 if dsim.local is None else dsim.local.wall_resultants()[5, 2]
        assert comm.allreduce(int(share != 0.0), op=MPI.SUM) >= 2
    assert abs(mean_force_ratio(dsim) / mean_force_ratio(sim) - 1) <= 1e-11
    err = np.abs(first[1] - first[0]).max(axis=0) / np.abs(first[0]).max(axis=0)
    assert err.max() <= 1e-11, err
    assert np.abs(np.diff(first[0][:, 1])).min() > 0  # the plate moves
    bits = comm.allgather(dsim.wall_forces().tobytes())
    assert all(b == bits[0] for b in bits)
    out = dsim.gather()
    err = comm.bcast(None if out is None else
                     float(np.abs(out["x"] - sim.p.x).max() / np.abs(sim.p.x).max()))
    assert err <= 1e-12, err
    a = dem.relax(sim, tol=0.02, controllers=[servo], ratio=mean_force_ratio)
    b = dem.relax(dsim, tol=0.02, controllers=[servo], ratio=mean_force_ratio)
    assert b["ratio"] < 0.02 and abs(servo.stress(dsim) / TARGET - 1) <= 0.02
    # (measured: the same steps, ratios 3e-12 apart, the plates 2e-12 R)
    assert a["steps"] == b["steps"] > 1000
    for k in ("ratio", "energy_removed"):
        assert abs(b[k] / a[k] - 1) <= 1e-8, k
    assert abs(dsim.walls.point[5, 2] - sim.walls.point[5, 2]) <= 1e-9 * R
    assert sim.walls.point[5, 2] < first[0][0, 1] - 1e-3 * R  # it compressed the packing
    # free_only: the column's spheres have no contact with the plate on any rank
    s = dsim.local
    touching = 0 if s is None else int(np.isin(dsim.gid[s.nl.wi], col).sum())
    assert comm.allreduce(touching) == 0


@pytest.mark.mpi
def test_a_true_hook_ends_the_call_on_every_rank():
    """As `Simulation.step`: the hook runs once a step, and its true return (the same on
    every rank) ends the call after that step, the run as the serial one."""
    from mpi4py import MPI

    sim, dsim, _, _ = runs(MPI.COMM_WORLD)
    for run in (sim, dsim):
        calls = []

        def seventh(calls=calls):
            calls.append(1)
            return len(calls) == 7

        assert run.step(20, hook=seventh) == 7 and run.nsteps == 7 and len(calls) == 7
        assert run.step(3) == 3
    out = dsim.gather()
    err = dsim.comm.bcast(None if out is None else float(np.abs(out["x"] - sim.p.x).max()))
    assert err <= 1e-12 * R
