"""The iterated DE x FE exchange of the penetration (``interface = "iqn-ils"``): each FE step
converges to its tolerance where the loose exchange diverges (a continuum 1000x stiffer than
the grains), and a restart continues it exactly (the accelerator's pairs are checkpointed)."""

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import numpy as np
import pytest

from coupling.apps.penetration.coupled import CoupledPenetration, CouplingUnstable, PenetrationParameters

# the stability benchmark's scene (benchmarks/stability.py), pushed 6 mm
BASE = dict(settle_time=0.08, depth=0.006, chamber_width=0.2, chamber_depth=0.12, radius=2e-3,
            element_size_far=0.03, continuum_stiffness=1000.0)


@pytest.fixture(scope="module")
def stiff(tmp_path_factory):
    comm = MPI.COMM_WORLD
    prm = PenetrationParameters(**BASE, interface="iqn-ils", interface_tol=1e-3)
    cpt = CoupledPenetration(prm, comm, log=lambda m: None)
    where = comm.bcast(str(tmp_path_factory.mktemp("ckpt")) if comm.rank == 0 else None, root=0)
    cpt.run(steps=5)
    cpt.save_checkpoint(where)
    cpt.run()
    return prm, cpt, where


@pytest.mark.slow
def test_loose_exchange_diverges_on_a_stiff_continuum():
    prm = PenetrationParameters(**BASE)
    cpt = CoupledPenetration(prm, MPI.COMM_WORLD, log=lambda m: None)
    with pytest.raises(CouplingUnstable, match="coupling unstable"):
        cpt.run()


@pytest.mark.mpi
def test_iterated_exchange_converges_every_step(stiff):
    prm, cpt, _ = stiff
    assert len(cpt.history) == cpt.n_steps
    its = np.array([h["interface_iterations"] for h in cpt.history])
    assert all(h["interface_converged"] for h in cpt.history), [h["interface_residual"] for h in cpt.history]
    assert its.max() <= prm.interface_max_iterations and its.mean() < 8
    qc = np.array([h["q_c"] for h in cpt.history])
    assert np.all(np.isfinite(qc)) and qc[-1] > 0


@pytest.mark.mpi
def test_iterated_exchange_restarts_exactly(stiff):
    prm, cpt, where = stiff
    again = CoupledPenetration(prm, cpt.comm, log=lambda m: None, checkpoint=where)
    assert len(again.history) == 5
    again.run()
    keys = ("q_c", "depth", "interface_iterations", "interface_residual")
    a = np.array([[h[k] for k in keys] for h in cpt.history], dtype=float)
    b = np.array([[h[k] for k in keys] for h in again.history], dtype=float)
    assert a.shape == b.shape
    assert np.allclose(a, b, rtol=1e-9, atol=1e-12 * np.abs(a).max())
