"""How many numba threads, on which threading layer (imported first by `dem`).

OpenMP before TBB: a parallel region costs ~1.5 us under GNU OpenMP and ~11 us under TBB on
the project's 2-vCPU VM (median of 2000 back-to-back launches), and a DEM step opens up to
four; the layer is picked at the first parallel launch, so this runs before it.

Under mpiexec, the ranks of one node share its cores: each rank gets cores / ranks threads.
Two ranks forking two threads each on two cores make every parallel region wait for a
descheduled thread (the settle benchmark fell from ~10 to ~1 M particle-steps/s). The
launchers' own variables give the ranks per node without an MPI call (MPICH/Hydra
``MPI_LOCALNRANKS``, Open MPI ``OMPI_COMM_WORLD_LOCAL_SIZE``).

An explicit ``NUMBA_NUM_THREADS``, ``NUMBA_THREADING_LAYER`` or
``NUMBA_THREADING_LAYER_PRIORITY`` is left alone.

Threads wait for work by spinning (libgomp's default), as in any OpenMP code: on cores that
other jobs keep busy, set ``NUMBA_NUM_THREADS=1`` (settle scene, 10k grains, both cores busy
with other processes: 2 spinning threads 2-5, 1 thread 12-14 M particle-steps/s; sleeping
waiters, ``OMP_WAIT_POLICY=PASSIVE``, 12-15 there but 10-12 instead of 23 on idle cores,
where 1 thread gives 19).
"""

import os

import numba

if "NUMBA_THREADING_LAYER" not in os.environ and \
        "NUMBA_THREADING_LAYER_PRIORITY" not in os.environ:
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]


def node_ranks() -> int:
    """MPI ranks on this node according to the launcher (1 outside mpiexec)."""
    for key in ("MPI_LOCALNRANKS", "OMPI_COMM_WORLD_LOCAL_SIZE"):
        if os.environ.get(key, "").isdigit():
            return max(1, int(os.environ[key]))
    return 1


def cores() -> int:
    """Cores this process may run on (mpiexec may bind a rank to fewer than the node's)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


if "NUMBA_NUM_THREADS" not in os.environ and node_ranks() > 1:
    numba.set_num_threads(max(1, min(numba.config.NUMBA_NUM_THREADS,
                                     cores() // node_ranks())))
