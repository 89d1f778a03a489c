"""An output directory is owned by one run.

``granfe run`` writes ``scene.toml`` and ``run.json`` (the run's fingerprint: a sha256 of
the canonical scene values, the code version and the rank count) into ``--out`` before
anything else, and refuses a directory that holds another run unless ``--overwrite``.
Checkpoints carry the same fingerprint; ``granfe restart`` compares it with the fingerprint
of the directory's ``scene.toml`` and names the keys that differ. Keys that may change
between a run and its restart (outputs, the punch's solver settings and step count) are left
out of the fingerprint.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from pathlib import Path

__all__ = ["RUN_FILE", "RunDirError", "fingerprint", "differences", "claim", "code_version"]

RUN_FILE = "run.json"

# what marks a directory as holding a run (besides run.json: scene.toml and one of these, the
# outputs of runs from before run.json)
_RUN_MARKS = ("checkpoint", "checkpoint.prev", "history.json", "results.json", "last_good")


class RunDirError(RuntimeError):
    """The output directory cannot be used (another run in it, not writable); exit code 2."""


def code_version() -> str:
    """The installed granfe version (part of a run's fingerprint)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("granfe")
    except PackageNotFoundError:
        return "unknown"


def fingerprint(scene, ranks: int) -> dict:
    """The values of ``scene`` that a restart must keep, their sha256 with the code version
    and the rank count."""
    from coupling.applications import application

    mutable = application(scene.scene.kind).restart_mutable
    values = {f"{s}.{k}": v for s, table in scene.to_dict().items() for k, v in table.items()
              if not f"{s}.{k}".startswith(mutable)}
    version = code_version()
    canonical = json.dumps({"values": values, "code_version": version, "ranks": ranks},
                           sort_keys=True, default=repr)
    return {"sha256": hashlib.sha256(canonical.encode()).hexdigest(), "values": values,
            "code_version": version, "ranks": int(ranks)}


def differences(saved: dict, current: dict) -> list[str]:
    """What differs between two fingerprints, as readable items naming the scene keys."""
    out = []
    a, b = saved.get("values", {}), current.get("values", {})
    # scene.kind first: with another kind every key differs
    for key in sorted(set(a) | set(b), key=lambda k: (k != "scene.kind", k)):
        if a.get(key, "<absent>") != b.get(key, "<absent>"):
            out.append(f"{key} ({a.get(key, '<absent>')!r} in the checkpoint, "
                       f"{b.get(key, '<absent>')!r} in scene.toml)")
    if saved.get("code_version") != current.get("code_version"):
        out.append(f"code version ({saved.get('code_version')} in the checkpoint, "
                   f"{current.get('code_version')} now)")
    if saved.get("ranks") != current.get("ranks"):
        out.append(f"rank count (checkpoint written on {saved.get('ranks')} rank(s), restarted "
                   f"on {current.get('ranks')}: restart with mpiexec -n {saved.get('ranks')})")
    return out


def holds_run(out: Path) -> bool:
    """Whether ``out`` is the directory of a granfe run (the only kind --overwrite clears)."""
    if not out.is_dir():
        return False
    if (out / RUN_FILE).exists():
        return True
    return (out / "scene.toml").exists() and any((out / m).exists() for m in _RUN_MARKS)


def claim(out, scene, ranks: int, overwrite: bool = False) -> dict:
    """Make ``out`` this run's directory (rank 0 only): refuse one that holds another run
    (unless ``overwrite``, which clears it) or cannot be written; write ``scene.toml`` and
    ``run.json``. Returns the fingerprint."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise RunDirError(f"--out {out} is a file, not a directory; pick another --out")
    if holds_run(out):
        if not overwrite:
            previous = _describe(out)
            raise RunDirError(f"{out} already holds a run{previous}; use --overwrite to replace "
                              "it, or another --out (granfe restart continues a stopped run)")
        try:
            for child in out.iterdir():
                if child.is_dir() and not child.is_symlink():
                    shutil.rmtree(child)
                else:
                    child.unlink()
        except OSError as err:
            raise RunDirError(f"cannot clear {out} for --overwrite: {err}") from None
    fp = fingerprint(scene, ranks)
    try:
        out.mkdir(parents=True, exist_ok=True)
        (out / "scene.toml").write_text(scene.to_toml())
        (out / RUN_FILE).write_text(json.dumps({"fingerprint": fp, "kind": scene.scene.kind,
                                                "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")},
                                               indent=1, default=repr))
    except OSError as err:
        raise RunDirError(f"cannot write the output directory {out}: {err.strerror or err}; "
                          "pick another --out") from None
    return fp


def _describe(out: Path) -> str:
    try:
        info = json.loads((out / RUN_FILE).read_text())
        return f" (kind {info.get('kind')}, started {info.get('started')})"
    except (OSError, ValueError):
        return ""
