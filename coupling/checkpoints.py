"""Checkpoints written atomically and validated on read.

A checkpoint is a directory ``<base>`` (``out/checkpoint``) of files and a ``manifest.json``
with the sha256 of every file, the step, the rank count and the run's fingerprint
(:mod:`coupling.rundir`). It is written as ``<base>.tmp-<step>`` (every file fsynced, the
manifest last), then rotated into place: ``<base>`` -> ``<base>.prev``, then
``<base>.tmp-<step>`` -> ``<base>``. A kill at any moment leaves at least one complete
checkpoint; :func:`find_checkpoint` takes the newest one that validates (``<base>``, a
complete ``<base>.tmp-*`` or ``<base>.prev``) and says which ones it passed over and why.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from pathlib import Path

__all__ = ["MANIFEST", "CheckpointError", "DiskFull", "ensure_free_space", "write_checkpoint",
           "validate", "find_checkpoint", "set_aside_invalid"]

MANIFEST = "manifest.json"


class CheckpointError(RuntimeError):
    """No complete, valid checkpoint; the message lists what was found and why it was refused."""


class DiskFull(RuntimeError):
    """Too little free disk for the next output or checkpoint; nothing was written."""


#: free space kept in reserve besides twice the last checkpoint [bytes]
RESERVE = 64 * 2**20


def ensure_free_space(out, comm, what: str = "output") -> None:
    """Refuse (:class:`DiskFull`, on every rank) to write into ``out`` with less free disk
    than twice its last checkpoint plus :data:`RESERVE`. Writers that run out of disk midway
    (ADIOS2 aborts the process) never get the chance to, and the checkpoint already written
    stays the one a restart continues from."""
    out = Path(out)
    message = None
    if comm.rank == 0:
        last = out / "checkpoint"
        size = sum(f.stat().st_size for f in last.glob("*") if f.is_file()) if last.is_dir() else 0
        need = 2 * size + RESERVE
        free = shutil.disk_usage(out).free
        if free < need:
            kept = validate(last)[0]
            message = (f"only {free / 2**20:.0f} MB free in {out}, the next {what} needs about "
                       f"{need / 2**20:.0f} MB: free disk space, then "
                       + (f"continue from the checkpoint of step {kept['step']} with "
                          f"`granfe restart {out}`" if kept else "run again"))
    message = comm.bcast(message, root=0)
    if message:
        raise DiskFull(message)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_checkpoint(base, step: int, comm, write_files, meta: dict | None = None) -> Path:
    """Write a checkpoint of ``step`` atomically into ``base`` (collective).

    ``write_files(directory) -> list[str]`` writes this rank's files into ``directory`` and
    returns their names. ``meta`` (JSON) goes into the manifest. The previous checkpoint is
    kept as ``<base>.prev`` until the new one is complete and in place.

    A write that fails on any rank (a full disk, a quota) fails on every rank: the partial
    ``<base>.tmp-<step>`` is removed, the checkpoints already there are untouched, and
    :class:`CheckpointError` names the error and the checkpoint that is kept.
    """
    base = Path(base)
    tmp = base.parent / f"{base.name}.tmp-{step:06d}"
    error = None
    if comm.rank == 0:
        try:
            if tmp.exists():
                shutil.rmtree(tmp)
            tmp.mkdir(parents=True)
        except OSError as err:
            error = err
    if comm.bcast(error is not None, root=0):
        raise CheckpointError(f"could not write the checkpoint of step {step} in {tmp.parent}: "
                              f"{comm.bcast(str(error), root=0)}")
    digests = {}
    try:
        for name in write_files(tmp):
            _fsync(tmp / name)
            digests[name] = _sha256(tmp / name)
    except OSError as err:
        error = err
    errors = [e for e in comm.allgather(None if error is None else str(error)) if e]
    if errors:
        comm.barrier()
        if comm.rank == 0:
            shutil.rmtree(tmp, ignore_errors=True)
        kept = validate(base)[0] if comm.rank == 0 else None
        kept = comm.bcast(kept, root=0)
        raise CheckpointError(
            f"could not write the checkpoint of step {step} in {tmp.parent}: {errors[0]}; "
            + (f"the checkpoint of step {kept['step']} in {base} is kept" if kept
               else "no earlier checkpoint exists"))
    gathered = comm.gather(digests, root=0)
    if comm.rank == 0:
        files = {k: v for d in gathered for k, v in d.items()}
        manifest = {"format": 1, "step": int(step), "ranks": comm.size, "files": files,
                    "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **(meta or {})}
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1, default=float))
        _fsync(tmp / MANIFEST)
        _fsync(tmp)
        prev = base.parent / f"{base.name}.prev"
        if base.exists():
            if prev.exists():
                shutil.rmtree(prev)
            os.replace(base, prev)
        os.replace(tmp, base)
        _fsync(base.parent)
        for stale in base.parent.glob(f"{base.name}.tmp-*"):
            shutil.rmtree(stale, ignore_errors=True)
    comm.barrier()
    return base


def validate(directory) -> tuple[dict | None, str]:
    """(manifest, "") for a complete checkpoint whose files all match their sha256, else
    (None, the reason)."""
    directory = Path(directory)
    path = directory / MANIFEST
    if not directory.is_dir():
        return None, "missing"
    if not path.exists():
        return None, f"no {MANIFEST} (incomplete, or written by an older granfe)"
    try:
        manifest = json.loads(path.read_text())
        files, step = manifest["files"], int(manifest["step"])
    except (ValueError, KeyError, TypeError, OSError) as err:
        return None, f"{MANIFEST} is unreadable ({type(err).__name__})"
    for name, digest in files.items():
        f = directory / name
        if not f.exists():
            return None, f"{name} is missing"
        if _sha256(f) != digest:
            return None, f"{name} does not match its sha256 (truncated or corrupt)"
    manifest["step"] = step
    return manifest, ""


def find_checkpoint(base) -> tuple[Path, dict, list[str]]:
    """The newest valid checkpoint among ``<base>``, ``<base>.tmp-*`` and ``<base>.prev``:
    (its directory, its manifest, notes on the ones passed over). Raises
    :class:`CheckpointError` when none is valid."""
    base = Path(base)
    candidates = [base, *sorted(base.parent.glob(f"{base.name}.tmp-*")),
                  base.parent / f"{base.name}.prev"]
    found, refused = [], []
    for c in candidates:
        manifest, reason = validate(c)
        if manifest is not None:
            found.append((manifest["step"], c, manifest))
        elif c.exists():
            refused.append(f"{c}: {reason}")
    if not found:
        detail = "; ".join(refused) if refused else f"no {base} directory"
        raise CheckpointError(f"no complete checkpoint in {base.parent} to restart from ({detail})")
    step, path, manifest = max(found, key=lambda f: f[0])
    notes = list(refused)
    if path != base:
        notes.append(f"falling back to {path} (step {step})")
    return path, manifest, notes


def set_aside_invalid(base) -> Path | None:
    """Before continuing from a fallback: rename an invalid ``<base>`` to ``<base>.corrupt``
    (kept for inspection) so that the next checkpoint's rotation keeps the valid one as
    ``<base>.prev``. Returns the new name, or None when ``<base>`` is valid or absent."""
    base = Path(base)
    if not base.exists() or validate(base)[0] is not None:
        return None
    bad = base.parent / f"{base.name}.corrupt"
    if bad.exists():
        shutil.rmtree(bad)
    os.replace(base, bad)
    return bad
