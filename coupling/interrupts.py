"""SIGINT / SIGTERM during a run: finish the current step, write a checkpoint, stop.

:class:`StopRequests` records the signal (a second one stops at once); the run asks
:meth:`StopRequests.requested` once per step (an allreduce, so every rank stops after the
same step) and raises :class:`Interrupted` after its checkpoint. The command exits with
128 + the signal number (130 for SIGINT, 143 for SIGTERM).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from pathlib import Path

__all__ = ["Interrupted", "StopRequests"]

_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(Exception):
    """Stopped on a signal after step ``step``, the state in ``checkpoint`` (None: none)."""

    def __init__(self, signum: int, step: int, checkpoint: Path | None, out: Path):
        self.signum, self.step, self.checkpoint, self.out = signum, step, checkpoint, out
        name = signal.Signals(signum).name
        if checkpoint is None:
            msg = (f"stopped by {name} after step {step}; no checkpoint written (this run "
                   "writes none)")
        else:
            msg = f"stopped by {name} after step {step}; checkpoint (step {step}) in {checkpoint}"
        super().__init__(msg)

    @property
    def exit_code(self) -> int:
        return 128 + int(self.signum)


class StopRequests:
    """Context manager recording SIGINT / SIGTERM (main thread only; elsewhere a no-op).

    Libraries initialised during the set-up (PETSc, gmsh) replace the handlers; they are
    installed again at every :meth:`requested`, so a signal during the set-up itself still
    stops the process at once, without a checkpoint (there is none to write)."""

    def __init__(self, quiet: bool = False):
        self.signum, self.quiet = 0, quiet   # quiet: say nothing (the ranks other than 0)
        self._old: dict = {}

    def _handler(self, signum, frame):
        if self.signum:   # the second signal: stop at once
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        self.signum = signum
        if not self.quiet:
            print(f"\ngranfe: {signal.Signals(signum).name} received: stopping after the current "
                  "step, with a checkpoint where the run writes them (send it again to stop at "
                  "once)", file=sys.stderr, flush=True)

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for s in _SIGNALS:
                self._old[s] = signal.signal(s, self._handler)
        return self

    def _rearm(self):
        """Install the handlers again: PETSc's import and gmsh's initialize replace them at
        the C level without Python knowing."""
        if self._old and not self.signum:
            for s in _SIGNALS:
                signal.signal(s, self._handler)

    def __exit__(self, *exc):
        for s, h in self._old.items():
            signal.signal(s, h)
        self._old.clear()
        return False

    def requested(self, comm) -> int:
        """The signal any rank received (0: none); collective. Re-arms the handlers."""
        from mpi4py import MPI

        self._rearm()

        return int(comm.allreduce(self.signum, op=MPI.MAX))
