"""The ``granfe`` command: ``granfe run|check|restart``.

``mpiexec -n 2 granfe run scenes/punch_2d.toml --out output/punch --set window.half_width=0.08``
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="granfe", description="DE x micropolar FE coupled scenes")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run a scene")
    run.add_argument("scene", type=Path)
    run.add_argument("--out", type=Path, default=None, help="output directory (default output/<scene name>)")
    run.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                     help="override a scene value (repeatable)")
    run.add_argument("--no-progress", action="store_true")
    check = sub.add_parser("check", help="validate a scene and summarise its size")
    check.add_argument("scene", type=Path)
    check.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    restart = sub.add_parser("restart", help="continue a run from its last checkpoint")
    restart.add_argument("directory", type=Path)
    restart.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)

    from coupling.scene import SceneError, load_scene, parse_overrides

    try:
        if args.command in ("run", "check"):
            scene = load_scene(args.scene, parse_overrides(args.set))
    except SceneError as err:
        print(f"granfe: error in {args.scene}: {err}", file=sys.stderr)
        return 2

    if args.command == "check":
        from coupling.runner import summarise
        print(json.dumps({"scene": str(args.scene), "valid": True, **summarise(scene)}, indent=2))
        return 0
    if args.command == "run" and scene.scene.kind == "penetration":
        return _run_penetration(scene, args)
    if args.command == "restart":
        kind = _scene_kind(args.directory)
        if kind == "penetration":
            return _run_penetration(load_scene(args.directory / "scene.toml"), args, restart=True)

    from mpi4py import MPI

    from coupling.runner import RunStopped, restart_scene, run_scene

    try:
        if args.command == "run":
            out = args.out or Path("output") / scene.scene.name
            run_scene(scene, out, MPI.COMM_WORLD, progress=not args.no_progress)
        else:
            out = args.directory
            restart_scene(out, MPI.COMM_WORLD, progress=not args.no_progress)
    except (RunStopped, FileNotFoundError) as err:
        if MPI.COMM_WORLD.rank == 0:
            print(f"granfe: {err}", file=sys.stderr)
        return 1
    if MPI.COMM_WORLD.rank == 0:
        print(f"granfe: outputs in {out}")
    return 0


def _scene_kind(directory: Path) -> str | None:
    """The kind of the scene run in ``directory`` (None when it holds no scene.toml)."""
    import tomllib

    path = directory / "scene.toml"
    if not path.exists():
        return None
    return tomllib.loads(path.read_text()).get("scene", {}).get("kind", "bonded_punch")


def _run_penetration(scene, args, restart: bool = False) -> int:
    from mpi4py import MPI

    from coupling.penetration_run import run_penetration

    out = args.directory if restart else (args.out or Path("output") / scene.scene.name)
    comm = MPI.COMM_WORLD
    if comm.rank == 0 and not restart:
        out.mkdir(parents=True, exist_ok=True)
        (out / "scene.toml").write_text(scene.to_toml())
    o = scene.output
    try:
        run_penetration(scene.parameters(), out, comm, frames=o.frames, fields=o.fields,
                        particles=o.particles, png=o.png, progress=not args.no_progress,
                        checkpoint_every=o.checkpoint_every, restart=restart,
                        moving=scene.moving_parameters())
    except FileNotFoundError as err:
        if comm.rank == 0:
            print(f"granfe: {err}", file=sys.stderr)
        return 1
    except RuntimeError as err:
        if comm.rank == 0:
            print(f"granfe: {err}", file=sys.stderr)
        return 1
    if comm.rank == 0:
        print(f"granfe: outputs in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
