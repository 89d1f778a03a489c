"""Shared test set-up: MPI hygiene after each test (dolfinx python/test/conftest.py)."""

import gc
import os

import pytest

os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")
os.environ.setdefault("MPLBACKEND", "Agg")


def _comm():
    # dem tests must not need dolfinx: import MPI lazily, only if already loaded.
    import sys

    if "mpi4py.MPI" in sys.modules:
        return sys.modules["mpi4py.MPI"].COMM_WORLD
    return None


@pytest.fixture(autouse=True)
def _mpi_barrier_after_test():
    yield
    comm = _comm()
    if comm is not None and comm.size > 1:
        gc.collect()
        comm.Barrier()


@pytest.fixture
def tmp_out(tmp_path_factory):
    """An output directory shared by all ranks (rank 0 creates it, the name is broadcast)."""
    comm = _comm()
    if comm is None or comm.size == 1:
        return tmp_path_factory.mktemp("out")
    path = str(tmp_path_factory.mktemp("out")) if comm.rank == 0 else None
    return comm.bcast(path, root=0)
