"""Shared test set-up: MPI hygiene after each test (dolfinx python/test/conftest.py).

Under ``mpiexec`` the automatic garbage collector is off and cyclic garbage is collected
after every test, on every rank at once: PETSc objects held in reference cycles are destroyed
collectively, and a collection started on one rank during another's collective deadlocks
(:mod:`coupling.collective_gc`)."""

import gc
import os

import pytest

os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")
os.environ.setdefault("MPLBACKEND", "Agg")


def _launched_ranks() -> int:
    # the launcher's environment (MPICH / Hydra, Open MPI), read without initialising MPI
    for key in ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE"):
        if os.environ.get(key, "").isdigit():
            return int(os.environ[key])
    return 1


if _launched_ranks() > 1:
    gc.disable()


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
