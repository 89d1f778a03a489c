"""The same coupled scene on the same number of ranks gives the same bits run to run.

Grains amplify round-off about tenfold per FE step, so any run-to-run difference in the FE
solve becomes a different trajectory within tens of steps: with parallel MUMPS (dynamic
scheduling) two 2-rank runs of this scene first differed at FE step 15. The penetration's
continuum is therefore solved with :data:`granfe.solvers.REDUNDANT`."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
GRANFE = Path(sys.executable).parent / "granfe"
MPIEXEC = Path(sys.executable).parent / "mpiexec"
SCENE = ["scenes/cpt_2d.toml", "--no-progress", "--set", "penetrator.depth=0.006", "--set",
         "grains.settle_time=0.05", "--set", "output.png=false", "--set", "output.fields=false",
         "--set", "output.particles=false", "--set", "output.checkpoint_every=0"]


def _history(out: Path, ranks: int) -> list[dict]:
    cmd = [str(MPIEXEC), "-n", str(ranks), str(GRANFE), "run", *SCENE, "--out", str(out)]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads((out / "results.json").read_text())["history"]


@pytest.mark.slow
@pytest.mark.skipif(not (GRANFE.exists() and MPIEXEC.exists()), reason="needs the venv's granfe and mpiexec")
def test_two_rank_runs_are_bit_identical(tmp_path):
    a, b = _history(tmp_path / "a", 2), _history(tmp_path / "b", 2)
    assert len(a) == len(b) > 40
    keys = ("q_c", "f_s", "depth", "interface_mismatch")
    first = next((k for k, (x, y) in enumerate(zip(a, b, strict=True)) if any(x[q] != y[q] for q in keys)), None)
    assert first is None, f"the runs first differ at FE step {first + 1}"
