"""Collective helpers over the MPI ranks: mpi4py on first use, rows sent to ranks, float
arrays summed in rank order (the same bits everywhere), one error raised on every rank."""

from __future__ import annotations

import numpy as np

_MPI = None


def _mpi():
    """mpi4py.MPI, imported on first use (``import dem`` stays free of MPI)."""
    global _MPI
    if _MPI is None:
        from mpi4py import MPI

        _MPI = MPI
    return _MPI


def _spec(buf, rows_per_rank):
    """mpi4py buffer spec [buf, (counts, displacements), DOUBLE] for rows of buf."""
    c = np.asarray(rows_per_rank, np.int64) * (buf.shape[1] if buf.ndim > 1 else 1)
    return [buf, (c, np.concatenate([[0], np.cumsum(c)[:-1]])), _mpi().DOUBLE]


def _exchange_rows(comm, rows, dest):
    """Send row k of rows (n, K) float64 to rank dest[k]; returns the rows received (m, K),
    ordered by source rank, then by the sender's order."""
    order = np.argsort(dest, kind="stable")
    send = np.ascontiguousarray(rows[order])
    scount = np.bincount(dest, minlength=comm.size).astype(np.int64)
    rcount = np.empty_like(scount)
    comm.Alltoall(scount, rcount)
    recv = np.empty((int(rcount.sum()), rows.shape[1]))
    comm.Alltoallv(_spec(send, scount), _spec(recv, rcount))
    return recv


def _in_rank_order(parts) -> np.ndarray:
    """parts[0] + parts[1] + ... (one part a rank, in rank order)."""
    total = parts[0].copy()
    for r in range(1, len(parts)):
        total += parts[r]
    return total


def _rank_sum(comm, a) -> np.ndarray:
    """The sum of the float array ``a`` over the ranks, added in rank order: the same bits on
    every rank and every run (an Allreduce leaves the order to the MPI library)."""
    a = np.ascontiguousarray(a, float)
    if comm.size == 1:
        return a.copy()
    parts = np.empty((comm.size,) + a.shape)
    comm.Allgather(a, parts)
    return _in_rank_order(parts)


def _agree(comm, error):
    """Raise on every rank the error (an exception or a message) of the first rank that has
    one, so that no rank is left waiting in a collective call."""
    bad = [e for e in comm.allgather(error) if e is not None]
    if bad:
        raise bad[0] if isinstance(bad[0], Exception) else ValueError(bad[0])
