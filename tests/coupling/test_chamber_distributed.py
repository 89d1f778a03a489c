"""The 3D calibration chamber's full DEM (`DemPenetration`) on a `dem.DistributedSimulation`
equals the serial run.

What differs from the serial run is the order of one sum: the top plate's force, added over
the ranks (`DistributedSimulation.wall_forces`); its round-off reaches the servo's speed at
every step of the consolidation (2750 here) and grows in the packing. Measured on 2 ranks:
q_c within 9e-13 of its largest value over the push; the bound, 1e-8, leaves room for the
packing's amplification of round-off and still fails on any change of contact, of the
clump's forces or of the servo's timing (those move q_c by percents).
"""

from types import SimpleNamespace

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest

from coupling.apps.penetration.coupled import DemPenetration, PenetrationParameters

# tests/coupling/test_chamber.py's 3D chamber, 2 cm deep: 4624 spheres of 1.5 mm, a cone of 4
# grain radii, 50 kPa under the top plate, a push of 4 mm in 6 blocks
CHAMBER_3D = dict(dim=3, chamber_width=0.075, chamber_depth=0.02, radius=1.5e-3, cone_radius=0.006,
                  velocity=1.0, depth=0.004, vertical_stress=5e4, consolidation_tol=1e-2,
                  window_half_width=0.0135, window_depth=0.025, element_size_window=0.005,
                  element_size_far=0.02, substeps=50)


@pytest.mark.mpi
def test_3d_full_dem_on_ranks_equals_serial():
    """The model on every rank of COMM_WORLD (distributed on 2) against a serial one built on
    each rank: the same steps, q_c history and plate to round-off, the same bits on every
    rank; the plate holds its stress."""
    comm = MPI.COMM_WORLD
    prm = PenetrationParameters(**CHAMBER_3D)
    serial = DemPenetration(prm, log=lambda m: None)
    q_serial = np.array([h["q_c"] for h in serial.run()])
    model = DemPenetration(prm, log=lambda m: None, comm=comm)
    assert model.distributed == (comm.size > 1)
    q = np.array([h["q_c"] for h in model.run()])
    assert model.sim.nsteps == serial.sim.nsteps and len(q) == len(q_serial) == 6
    assert np.abs(q - q_serial).max() <= 1e-8 * np.abs(q_serial).max()
    assert q_serial[-1] > 0.5 * prm.vertical_stress  # the cone is in the grains
    assert all(np.array_equal(other, q) for other in comm.allgather(q))
    plate = 5  # the top plate: after the four sides and the base
    assert abs(model.sim.walls.point[plate, 2] - serial.sim.walls.point[plate, 2]) <= 1e-9 * prm.radius
    (servo,) = model.servos
    assert servo.stress(model.sim) == pytest.approx(prm.vertical_stress, rel=0.1)


def test_distributed_full_dem_is_the_3d_chamber():
    """More than one rank: the 2D chamber (whose surcharge and BC1 servos read every
    particle) is refused, named."""
    prm = PenetrationParameters(**(CHAMBER_3D | dict(dim=2, kn=5e7)))
    with pytest.raises(ValueError, match="the 3D chamber only"):
        DemPenetration(prm, log=lambda m: None, comm=SimpleNamespace(size=2, rank=0))
