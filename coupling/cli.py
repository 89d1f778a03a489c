"""The ``granfe`` command: ``granfe run|check|restart``.

``mpiexec -n 2 granfe run scenes/punch_2d.toml --out output/punch --set window.half_width=0.08``

Exit codes: 0 done; 1 the run failed (the message says where its last state is); 2 a user
error (scene, output directory, checkpoint that does not belong to the scene), named, before
anything expensive; 128 + the signal number when stopped by SIGINT (130) or SIGTERM (143)
after writing a checkpoint.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

USER_ERROR, RUN_FAILED = 2, 1


class UserError(Exception):
    """A problem the user fixes (exit code 2); the message names the key or the file."""


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="granfe", description="DE x micropolar FE coupled scenes")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run a scene")
    run.add_argument("scene", type=Path)
    run.add_argument("--out", type=Path, default=None,
                     help="output directory (default output/<scene name>)")
    run.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                     help="override a scene value (repeatable)")
    run.add_argument("--overwrite", action="store_true",
                     help="clear an output directory that holds another run")
    run.add_argument("--no-progress", action="store_true")
    check = sub.add_parser("check", help="validate a scene and estimate its size, memory and time")
    check.add_argument("scene", type=Path)
    check.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    check.add_argument("--ranks", type=int, default=None,
                       help="MPI ranks the run will use (default: this command's)")
    restart = sub.add_parser("restart", help="continue a run from its last checkpoint")
    restart.add_argument("directory", type=Path)
    restart.add_argument("--no-progress", action="store_true")
    return parser


def main(argv: list[str] | None = None) -> int:
    """The ``granfe`` command; returns the exit code (0 done, 1 failed, 2 user error, 130 / 143 signal)."""
    args = _parser().parse_args(argv)
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    try:
        return {"check": _check, "run": _run, "restart": _restart}[args.command](args, comm)
    except UserError as err:
        _say(comm, f"granfe: {err}")
        return USER_ERROR


def _say(comm, msg: str, err: bool = True) -> None:
    if comm.rank == 0:
        print(msg, file=sys.stderr if err else sys.stdout, flush=True)


def _scene(path: Path, sets: list[str], what: str | None = None):
    from coupling.scene import SceneError, load_scene, parse_overrides

    try:
        return load_scene(path, parse_overrides(sets))
    except SceneError as err:
        raise UserError(f"error in {what or path}: {err}") from None


def _preflight(scene, ranks: int, what) -> dict:
    from coupling.preflight import preflight
    from coupling.scene import SceneError

    try:
        return preflight(scene, ranks)
    except SceneError as err:
        raise UserError(f"error in {what}: {err}") from None


def _check(args, comm) -> int:
    scene = _scene(args.scene, args.set)
    ranks = args.ranks if args.ranks is not None else comm.size
    if ranks < 1:
        raise UserError(f"--ranks must be >= 1, got {ranks}")
    info = _preflight(scene, ranks, args.scene)
    if comm.rank == 0:
        print(json.dumps({"scene": str(args.scene), "valid": True, "ranks": ranks, **info},
                         indent=2))
        for w in info["warnings"]:
            print(f"granfe: warning: {w}", file=sys.stderr)
    return 0


def _run(args, comm) -> int:
    from coupling.rundir import RunDirError, claim

    scene = _scene(args.scene, args.set)
    info = _preflight(scene, comm.size, args.scene)
    for w in info["warnings"]:
        _say(comm, f"granfe: warning: {w}")
    out = args.out or Path("output") / scene.scene.name
    fp, error = None, None
    if comm.rank == 0:
        try:
            fp = claim(out, scene, comm.size, overwrite=args.overwrite)
        except RunDirError as err:
            error = str(err)
    fp, error = comm.bcast((fp, error), root=0)
    if error:
        raise UserError(error)
    return _execute(scene, out, comm, args, meta={"fingerprint": fp, "kind": scene.scene.kind})


def _restart(args, comm) -> int:
    from coupling.checkpoints import CheckpointError, find_checkpoint
    from coupling.rundir import differences, fingerprint

    d = args.directory
    if not d.is_dir():
        raise UserError(f"{d} is not a directory: restart takes the --out directory of a run")
    if not (d / "scene.toml").is_file():
        raise UserError(f"{d} holds no scene.toml: not the output directory of a granfe run")
    scene = _scene(d / "scene.toml", [], what=f"{d / 'scene.toml'} (fix it; a restart keeps the "
                   "scene of its checkpoint)")
    _preflight(scene, comm.size, d / "scene.toml")
    found, error = None, None
    if comm.rank == 0:
        try:
            found = find_checkpoint(d / "checkpoint")
        except CheckpointError as err:
            error = str(err)
    found, error = comm.bcast((found, error), root=0)
    if error:
        _say(comm, f"granfe: {error}; nothing to restart: run the scene again "
                   f"(granfe run {d / 'scene.toml'} --out {d} --overwrite)")
        return RUN_FAILED
    path, manifest, notes = found
    current = fingerprint(scene, comm.size)
    diffs = differences(manifest.get("fingerprint", {}), current)
    if diffs:
        shown = diffs[:8] + ([f"and {len(diffs) - 8} more"] if len(diffs) > 8 else [])
        raise UserError(f"the checkpoint in {path} (step {manifest['step']}) does not belong to "
                        f"{d / 'scene.toml'}; they differ in: " + "; ".join(shown)
                        + ". Restore those values, or start a new run with --overwrite or "
                        "another --out")
    for note in notes:
        _say(comm, f"granfe: {note}")
    if comm.rank == 0 and path != d / "checkpoint":
        from coupling.checkpoints import set_aside_invalid

        bad = set_aside_invalid(d / "checkpoint")
        if bad is not None:
            print(f"granfe: the invalid checkpoint is kept as {bad}", file=sys.stderr)
    comm.barrier()
    _say(comm, f"granfe: restarting from {path} (step {manifest['step']})", err=False)
    return _execute(scene, d, comm, args, meta={"fingerprint": current, "kind": scene.scene.kind},
                    checkpoint=path)


def _execute(scene, out: Path, comm, args, meta: dict, checkpoint: Path | None = None) -> int:
    """Run (or continue from ``checkpoint``) with SIGINT / SIGTERM stopping after a step."""
    from coupling.applications import application
    from coupling.interrupts import Interrupted, StopRequests

    try:
        with StopRequests(quiet=comm.rank != 0) as stop:
            run = application(scene.scene.kind).load("run")
            run(scene, out, comm, progress=not args.no_progress, checkpoint=checkpoint, stop=stop,
                meta=meta)
    except Interrupted as err:
        mpi = f"mpiexec -n {comm.size} " if comm.size > 1 else ""
        _say(comm, f"granfe: {err}" + (f"; continue with: {mpi}granfe restart {out}"
                                       if err.checkpoint is not None else ""))
        return err.exit_code
    except (RuntimeError, FileNotFoundError) as err:   # RunStopped, CheckpointError are RuntimeErrors
        _say(comm, f"granfe: {err}")
        return RUN_FAILED
    _say(comm, f"granfe: outputs in {out}", err=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
