"""Garbage collection at the same point on every MPI rank.

PETSc objects (a ``NonlinearProblem``'s matrices, a KSP) are destroyed collectively. Held in
a reference cycle, they die when Python's cyclic collector runs, and that moment depends on
each rank's own allocations: a collection that starts on one rank while the other waits in a
collective deadlocks both (seen under ``mpiexec -n 2``: one rank in ``NonlinearProblem.
__del__``, the other in the JIT's allreduce). Under MPI the automatic collector is therefore
switched off for a run and :func:`collect` is called where every rank is (output frames).
"""

from __future__ import annotations

import gc
from contextlib import contextmanager

__all__ = ["collective_gc", "collect"]


@contextmanager
def collective_gc(comm):
    """Within this block, on more than one rank, cyclic garbage is collected only by
    :func:`collect` (and once at the end, on every rank)."""
    if comm is None or comm.size == 1:
        yield
        return
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.collect()
        if enabled:
            gc.enable()


def collect(comm) -> None:
    """Collect cyclic garbage now; call it at a point every rank reaches in the same order."""
    if comm is not None and comm.size > 1:
        gc.collect()
