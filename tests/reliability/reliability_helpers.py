"""Helpers of the reliability tests: the ``granfe`` command in a subprocess (so that
exit codes, signals and tracebacks are the user's), tiny scenes, and waiting for a checkpoint."""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent

# a bonded punch of ~100 grains, a few load steps (~2 s a run)
PUNCH = ["scenes/punch_2d.toml", "--set", "geometry.width=0.2", "--set", "geometry.height=0.1",
         "--set", "geometry.element_size=0.02", "--set", "particles.radius=0.004",
         "--set", "window.half_width=0.06", "--set", "window.depth=0.05",
         "--set", "penetrator.steps=3", "--set", "output.png=false", "--set", "output.fields=false"]

# a 2D cone into ~1000 disks: settle 0.02 s, ~37 FE steps, a checkpoint every 2 (~5 s a run)
CPT = ["scenes/cpt_2d.toml", "--set", "grains.settle_time=0.02", "--set", "penetrator.depth=0.008",
       "--set", "penetrator.velocity=0.4", "--set", "output.png=false", "--set", "output.frames=1",
       "--set", "output.fields=false", "--set", "output.checkpoint_every=2",
       "--set", "chamber.element_size_window=0.012"]


def command(*args, ranks: int = 1) -> list[str]:
    exe = [str(BIN / "granfe")]
    if not (BIN / "granfe").exists():
        exe = [sys.executable, "-m", "coupling.cli"]
    if ranks > 1:
        exe = [str(BIN / "mpiexec"), "-n", str(ranks), *exe]
    return exe + [str(a) for a in args]


def _env():
    return {**os.environ, "NUMBA_NUM_THREADS": "1"}


def granfe(*args, ranks: int = 1, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(command(*args, ranks=ranks), cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout, env=_env())


def start(*args, ranks: int = 1) -> subprocess.Popen:
    return subprocess.Popen(command(*args, ranks=ranks), cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=_env())


def checkpoint_step(out: Path) -> int:
    """The step of ``out/checkpoint`` (-1: none yet)."""
    try:
        return json.loads((out / "checkpoint" / "manifest.json").read_text())["step"]
    except (OSError, ValueError, KeyError):
        return -1


def wait_for_checkpoint(proc: subprocess.Popen, out: Path, step: int, timeout: float = 120) -> None:
    """Wait until ``out`` holds a checkpoint of at least ``step`` (the run still going)."""
    t0 = time.monotonic()
    while checkpoint_step(out) < step:
        if proc.poll() is not None:
            raise AssertionError(f"the run ended (rc {proc.returncode}) before checkpoint {step}: "
                                 f"{proc.stderr.read()[-2000:]}")
        if time.monotonic() - t0 > timeout:
            proc.kill()
            raise AssertionError(f"no checkpoint {step} in {timeout} s")
        time.sleep(0.02)


def history(out: Path) -> list[tuple]:
    """(step, depth, q_c) of a penetration run's results."""
    h = json.loads((out / "results.json").read_text())["history"]
    return [(r["step"], r["depth"], r["q_c"], r["f_s"]) for r in h]
