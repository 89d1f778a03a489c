"""One runner for every application: steps, progress, frames, checkpoints, stops, failures.

An application hands the runner an object with the :class:`Steps` shape (its set-up done,
its history restored on a restart); the runner owns the loop and everything around it:

- a progress bar (tqdm, rank 0) with the application's figures of the step;
- frames every ``frame_every`` steps and at the last: the continuum as a VTX series
  (:class:`granfe.io.ContinuumWriter`; a restart starts ``<name>_from<step>``, VTX cannot
  append) and the grains as one VTU/PVD series continued across restarts
  (:class:`dem.io.ParticleWriter`);
- ``history.json`` and ``<history_name>.csv``: at every frame and checkpoint, and at the end
  (after the application's ``finish``, which may add columns derived from the whole
  history), always before the checkpoint of the same step (a kill between the two repeats
  the step);
- checkpoints every ``checkpoint_every`` steps (:mod:`coupling.checkpoints`), free disk
  space checked first (:func:`coupling.checkpoints.ensure_free_space`);
- a signal (:class:`coupling.interrupts.StopRequests`): checkpoint, then
  :class:`coupling.interrupts.Interrupted`;
- a failure the application names (``Steps.failures``): its last good state in
  ``out/last_good`` and the history so far, then :class:`RunStopped`.

Cyclic garbage is collected at frames only, at the same point on every rank
(:mod:`coupling.collective_gc`).
"""

from __future__ import annotations

import csv
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from coupling.checkpoints import ensure_free_space
from coupling.collective_gc import collect, collective_gc

__all__ = ["Outputs", "Steps", "RunStopped", "run_steps", "write_history"]


class RunStopped(RuntimeError):
    """A step failed for good; the message says where the last good state is."""


@dataclass(frozen=True)
class Outputs:
    """What a run writes, and how often (in steps)."""

    frame_every: int = 1
    fields: bool = True
    particles: bool = True
    png: bool = True
    checkpoint_every: int = 0        # 0: none
    checkpoint_at_start: bool = False
    checkpoint_at_end: bool = False

    def __post_init__(self):
        if self.frame_every < 1:
            raise ValueError(f"frame_every must be >= 1, got {self.frame_every!r}")
        if self.checkpoint_every < 0:
            raise ValueError(f"checkpoint_every must be >= 0, got {self.checkpoint_every!r}")


class Steps(Protocol):
    """What an application's run gives the runner."""

    name: str                          # progress label
    unit: str                          # what one step is ("step", "FE step")
    history_name: str                  # the CSV's stem
    particle_name: str                 # the grains' VTU/PVD series
    n_steps: int                       # steps of the whole run
    history: list[dict]                # one record per completed step (restored on restart)
    problem: object                    # the continuum (its fields are written at frames)
    failures: tuple[type[BaseException], ...]   # errors that stop the run, last state kept

    def advance(self) -> dict: ...                        # one step; its history record
    def frame_time(self, record: dict) -> float: ...      # strictly increasing
    def particles(self) -> dict | None: ...               # x, radius and point data (collective)
    def postfix(self, record: dict) -> dict: ...          # the progress bar's figures
    def save_checkpoint(self, directory: Path, meta: dict | None) -> None: ...   # collective
    def save_last_good(self, where: Path) -> None: ...    # collective
    def stopped(self, err: BaseException, where: Path) -> str: ...   # why, and where
    def finish(self) -> None: ...                         # columns of the whole history
    def figures(self, out: Path) -> None: ...             # collective


def write_history(out: Path, rows: list[dict], csv_name: str, header: dict | None = None) -> None:
    """``history.json`` (``header`` and the rows) and ``<csv_name>.csv`` (rank 0 only)."""
    (out / "history.json").write_text(json.dumps({**(header or {}), "steps": rows}, indent=1, default=float))
    if rows:
        with open(out / f"{csv_name}.csv", "w", newline="") as f:
            wr = csv.DictWriter(f, fieldnames=list(rows[0]), extrasaction="ignore")
            wr.writeheader()
            wr.writerows(rows)


def _resume_series(writer, until: float) -> None:
    """Keep the frames of ``writer``'s existing ``.pvd`` up to time ``until`` (a restart
    continues the series; frames written after the checkpoint are written again)."""
    if not writer.pvd_path.exists():
        return
    entries = re.findall(r'timestep="([^"]+)"[^>]*file="([^"]+)"', writer.pvd_path.read_text())
    writer.frames = [(float(t), f) for t, f in entries if float(t) <= until * (1 + 1e-12)]


def run_steps(steps: Steps, out: str | Path, comm, outputs: Outputs, *, progress: bool = True,
              stop=None, meta: dict | None = None, header: dict | None = None) -> list[dict]:
    """Run ``steps`` from its current step to ``steps.n_steps`` into ``out``; returns the
    history. ``meta`` goes into every checkpoint's manifest, ``header`` into history.json."""
    with collective_gc(comm):
        return _loop(steps, Path(out), comm, outputs, progress, stop, meta, header)


def _loop(steps, out, comm, outputs, progress, stop, meta, header):
    start, n = len(steps.history), steps.n_steps
    if comm.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    comm.barrier()
    if outputs.checkpoint_every and outputs.checkpoint_at_start and start == 0:
        ensure_free_space(out, comm, "checkpoint")
        steps.save_checkpoint(out / "checkpoint", meta)
    writers = _writers(steps, out, comm, outputs, start)
    bar = None
    if progress and comm.rank == 0:
        from tqdm import tqdm
        bar = tqdm(total=n, initial=start, unit=steps.unit, desc=steps.name)
    try:
        for k in range(start, n):
            try:
                record = steps.advance()
            except steps.failures as err:
                where = out / "last_good"
                steps.save_last_good(where)
                if comm.rank == 0:
                    write_history(out, steps.history, steps.history_name, header)
                raise RunStopped(steps.stopped(err, where)) from err
            last = k + 1 == n
            saved = bool(outputs.checkpoint_every) and (k + 1) % outputs.checkpoint_every == 0 \
                and (outputs.checkpoint_at_end or not last)
            frame = (k + 1) % outputs.frame_every == 0 or last
            if saved or frame:
                ensure_free_space(out, comm, "checkpoint" if saved else "frame")
                if comm.rank == 0 and (saved or not last):   # the last step's: after finish()
                    write_history(out, steps.history, steps.history_name, header)
            if frame:
                collect(comm)
                _write_frame(steps, writers, record, outputs.particles)
            if saved:
                steps.save_checkpoint(out / "checkpoint", meta)
            if bar is not None:
                bar.set_postfix(**steps.postfix(record))
                bar.update(1)
            signum = stop.requested(comm) if stop is not None else 0
            if signum and not last:
                _interrupt(steps, out, comm, outputs, signum, saved, meta, header)
    finally:
        if bar is not None:
            bar.close()
        for w in writers:
            if w is not None:
                w.close()
    steps.finish()
    if comm.rank == 0:
        write_history(out, steps.history, steps.history_name, header)
    if outputs.png:
        steps.figures(out)
    return steps.history


def _interrupt(steps, out, comm, outputs, signum, saved, meta, header):
    """Stop on a signal: the step's checkpoint (unless just written, or the run writes none)."""
    from coupling.interrupts import Interrupted

    step = len(steps.history)
    if not outputs.checkpoint_every:
        raise Interrupted(signum, step, None, out)
    if not saved:
        if comm.rank == 0:
            write_history(out, steps.history, steps.history_name, header)
        steps.save_checkpoint(out / "checkpoint", meta)
    raise Interrupted(signum, step, out / "checkpoint", out)


def _writers(steps, out, comm, outputs, start):
    """The continuum's VTX writer (all ranks) and the grains' series (rank 0)."""
    from dem.io import ParticleWriter
    from granfe.io import ContinuumWriter

    fields = ContinuumWriter(steps.problem, out, name="continuum" + (f"_from{start:04d}" if start else "")) \
        if outputs.fields else None
    grains = None
    if outputs.particles and comm.rank == 0:
        grains = ParticleWriter(out, steps.particle_name)
        if start:
            _resume_series(grains, steps.frame_time(steps.history[-1]))
    return fields, grains


def _write_frame(steps, writers, record, particles: bool):
    fields, grains = writers
    t = steps.frame_time(record)
    if fields is not None:
        fields.write(t)
    if particles:   # on every rank: grains split over the ranks are gathered collectively
        data = steps.particles()
        if grains is not None:
            grains.write(t, data.pop("x"), data.pop("radius"), **data)
