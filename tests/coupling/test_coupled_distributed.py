"""The coupled 3D chamber's push with its grains split over the ranks (``distribute_grains``:
the consolidated window continued as a `dem.DistributedSimulation`) is the replicated run's
push to round-off, and a restart continues it to the bit.

What differs from the replicated run is the order of sums: a grain's contact forces added in
its local run's pair order and the top plate's force added over the ranks. The exchange
itself is exact (each ghost's and cone sphere's force comes from its one owner, the others
add zeros). Round-off grows through the packing, so the bound (1e-8 of the largest q_c over
a push of ~30 FE steps) leaves room for it and still fails on any change of contact, of the
ghosts' reactions or of the servo's timing (those move q_c by percents).
"""

from dataclasses import replace

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest

from coupling.apps.penetration.coupled import CoupledPenetration, PenetrationParameters

# tests/coupling/test_chamber.py's 3D chamber (2237 grains in the window), forces exchange
CHAMBER_3D = dict(dim=3, chamber_width=0.075, chamber_depth=0.045, radius=1.5e-3, cone_radius=0.006,
                  velocity=1.0, depth=0.004, vertical_stress=5e4, consolidation_tol=1e-2,
                  window_half_width=0.0135, window_depth=0.025, element_size_window=0.005,
                  element_size_far=0.02, substeps=10, relaxation=0.3, interface="forces")


@pytest.mark.mpi
@pytest.mark.skipif(MPI.COMM_WORLD.size == 1, reason="on one rank distribute_grains changes nothing")
@pytest.mark.parametrize("integrator", ["implicit", "explicit"])
def test_distributed_push_is_the_replicated_one(tmp_path, integrator):
    comm = MPI.COMM_WORLD
    prm = PenetrationParameters(**CHAMBER_3D, continuum_integrator=integrator)
    q_replicated = np.array([h["q_c"] for h in CoupledPenetration(prm, comm, log=lambda m: None).run()])
    split = replace(prm, distribute_grains=True)
    model = CoupledPenetration(split, comm, log=lambda m: None)
    assert model.distributed == (comm.size > 1)
    model.run(steps=len(q_replicated) // 2)
    ck = comm.bcast(tmp_path / "ck", root=0)
    model.save_checkpoint(ck)
    q = np.array([h["q_c"] for h in model.run()])
    assert len(q) == len(q_replicated) and q_replicated[-1] > 0
    assert np.abs(q - q_replicated).max() <= 1e-8 * np.abs(q_replicated).max()
    assert all(np.array_equal(other, q) for other in comm.allgather(q))
    # every particle, gathered in the serial order
    assert model.grain_state().n == model.n_grains + len(model.pen_index)
    again = CoupledPenetration(split, comm, log=lambda m: None, checkpoint=ck)
    assert np.array_equal([h["q_c"] for h in again.run()], q)


def test_distributed_grains_are_the_3d_chambers():
    with pytest.raises(ValueError, match="distribute_grains = true splits the 3D chamber"):
        PenetrationParameters(distribute_grains=True)
    with pytest.raises(ValueError, match="distribute_grains must be true or false"):
        PenetrationParameters(**CHAMBER_3D, distribute_grains=1)
