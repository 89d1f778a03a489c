"""Fixtures of the reliability tests: a tiny 2D penetration run without interruption, and
the same run stopped by SIGTERM (shared by the fault tests, which copy it)."""

import signal

import pytest
from reliability_helpers import CPT, granfe, history, start, wait_for_checkpoint


@pytest.fixture(scope="session")
def cpt_reference(tmp_path_factory):
    """The tiny 2D penetration run without interruption: its history."""
    out = tmp_path_factory.mktemp("reference") / "run"
    proc = granfe("run", *CPT, "--out", out, "--no-progress")
    assert proc.returncode == 0, proc.stderr[-3000:]
    return history(out)


@pytest.fixture(scope="session")
def cpt_stopped(tmp_path_factory):
    """The tiny 2D penetration stopped by SIGTERM after its second checkpoint: the directory
    (copy it before changing it), the process' exit code and stderr."""
    out = tmp_path_factory.mktemp("stopped") / "run"
    proc = start("run", *CPT, "--out", out, "--no-progress")
    wait_for_checkpoint(proc, out, 4)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    return out, proc.returncode, err
