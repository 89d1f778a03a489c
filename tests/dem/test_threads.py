"""dem.threads: ranks of one node share its cores; OpenMP is the preferred layer."""

import ctypes.util
import os
import subprocess
import sys

import pytest

SCRIPT = ("import dem, numba, numpy as np\n"
          "from numba import njit, prange\n"
          "@njit(parallel=True)\n"
          "def k(a):\n"
          "    for i in prange(a.shape[0]):\n"
          "        a[i] += 1.0\n"
          "k(np.zeros(8))\n"
          "print(numba.get_num_threads(), numba.threading_layer())")


def run(**env):
    base = {k: v for k, v in os.environ.items()
            if not k.startswith(("NUMBA_", "MPI_LOCAL", "OMPI_COMM_WORLD"))}
    out = subprocess.run([sys.executable, "-c", SCRIPT], env={**base, **env}, check=True,
                         capture_output=True, text=True, cwd=os.getcwd())
    threads, layer = out.stdout.split()
    return int(threads), layer


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two cores")
def test_ranks_share_the_node_cores():
    cores = len(os.sched_getaffinity(0))
    assert run()[0] == cores
    assert run(MPI_LOCALNRANKS=str(cores))[0] == 1  # MPICH / Hydra
    assert run(OMPI_COMM_WORLD_LOCAL_SIZE=str(cores))[0] == 1  # Open MPI
    assert run(MPI_LOCALNRANKS=str(cores), NUMBA_NUM_THREADS="2")[0] == 2  # asked for


def test_openmp_layer_first_unless_asked():
    layer = run()[1]
    if ctypes.util.find_library("gomp"):
        assert layer == "omp"
    else:
        assert layer in ("tbb", "workqueue")
    assert run(NUMBA_THREADING_LAYER="workqueue")[1] == "workqueue"
