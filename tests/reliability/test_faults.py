"""Faults a run survives (issue 15, items 1, 2, 5 and 6): a signal stops it with a checkpoint
and a restart continues to the same result as an uninterrupted run; a kill (SIGKILL) during
the run or during a checkpoint write, a corrupt or truncated checkpoint, fall back to the
last complete checkpoint; a directory belongs to one run; a restart refuses a checkpoint of
another scene or rank count, naming what differs."""

import json
import os
import shutil
import signal

import pytest
from reliability_helpers import (
    CPT,
    PUNCH,
    checkpoint_step,
    granfe,
    history,
    start,
    wait_for_checkpoint,
)


def _copy(stopped, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(stopped[0], out)
    return out


def _restart_equals_reference(out, reference, *expect_in_stderr):
    proc = granfe("restart", out, "--no-progress")
    assert proc.returncode == 0, proc.stderr[-3000:]
    for text in expect_in_stderr:
        assert text in proc.stderr, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    # serial restarts of the 2D penetration are bit-identical to the uninterrupted run
    assert history(out) == reference
    return proc


def test_sigterm_writes_a_checkpoint_and_restart_reaches_the_same_result(cpt_stopped, cpt_reference,
                                                                         tmp_path):
    out, rc, err = cpt_stopped
    assert rc == 143, err[-3000:]
    step = checkpoint_step(out)
    assert step >= 4
    assert f"stopped by SIGTERM after step {step}" in err and f"granfe restart {out}" in err
    out = _copy(cpt_stopped, tmp_path)
    proc = _restart_equals_reference(out, cpt_reference)
    assert f"restarting from {out / 'checkpoint'} (step {step})" in proc.stdout


def test_sigint_stops_with_130_and_restart_completes(tmp_path):
    out = tmp_path / "run"
    proc = start("run", *PUNCH, "--set", "penetrator.steps=200", "--out", out, "--no-progress")
    wait_for_checkpoint(proc, out, 2)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-3000:]
    step = checkpoint_step(out)
    assert f"stopped by SIGINT after step {step}" in err and "Traceback" not in err
    # finish sooner: the step count may change on restart of a bonded punch
    text = (out / "scene.toml").read_text().replace("steps = 200", f"steps = {step + 2}")
    (out / "scene.toml").write_text(text)
    proc = granfe("restart", out, "--no-progress")
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = json.loads((out / "history.json").read_text())["steps"]
    assert [h["step"] for h in rows] == list(range(1, step + 3))


def test_sigkill_during_the_run_then_restart_continues(cpt_reference, tmp_path):
    out = tmp_path / "run"
    proc = start("run", *CPT, "--out", out, "--no-progress")
    wait_for_checkpoint(proc, out, 2)
    proc.kill()
    proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    _restart_equals_reference(out, cpt_reference)


def test_half_written_checkpoint_is_ignored(cpt_stopped, cpt_reference, tmp_path):
    """Killed while writing the next checkpoint: a tmp directory with a truncated file and no
    manifest beside the complete one."""
    out = _copy(cpt_stopped, tmp_path)
    tmp = out / "checkpoint.tmp-000099"
    shutil.copytree(out / "checkpoint", tmp)
    (tmp / "manifest.json").unlink()
    data = (tmp / "grains.npz").read_bytes()
    (tmp / "grains.npz").write_bytes(data[: len(data) // 2])
    _restart_equals_reference(out, cpt_reference, "checkpoint.tmp-000099: no manifest.json")


def test_kill_between_the_renames_finds_the_new_checkpoint(cpt_stopped, cpt_reference, tmp_path):
    """Killed after the old checkpoint became .prev and before the new one took its name."""
    out = _copy(cpt_stopped, tmp_path)
    step = checkpoint_step(out)
    os.replace(out / "checkpoint", out / f"checkpoint.tmp-{step:06d}")
    _restart_equals_reference(out, cpt_reference,
                              f"falling back to {out}/checkpoint.tmp-{step:06d}")


@pytest.mark.parametrize("damage", ["truncated_npz", "garbage_state_json", "missing_file",
                                    "garbage_manifest"])
def test_damaged_checkpoint_falls_back_to_the_previous_one(damage, cpt_stopped, cpt_reference,
                                                           tmp_path):
    out = _copy(cpt_stopped, tmp_path)
    ck = out / "checkpoint"
    if damage == "truncated_npz":
        data = (ck / "continuum_rank0_of1.npz").read_bytes()
        (ck / "continuum_rank0_of1.npz").write_bytes(data[:100])
    elif damage == "garbage_state_json":
        (ck / "state.json").write_text('{"step": 1, "ranks"')
    elif damage == "missing_file":
        (ck / "grains.npz").unlink()
    else:
        (ck / "manifest.json").write_text("{not json")
    prev = json.loads((out / "checkpoint.prev" / "manifest.json").read_text())["step"]
    _restart_equals_reference(out, cpt_reference,
                              f"falling back to {out}/checkpoint.prev (step {prev})")
    assert (out / "checkpoint.corrupt").is_dir()   # set aside, not rotated into .prev


def test_no_valid_checkpoint_is_said_without_traceback(cpt_stopped, tmp_path):
    out = _copy(cpt_stopped, tmp_path)
    for ck in (out / "checkpoint", out / "checkpoint.prev"):
        data = (ck / "grains.npz").read_bytes()
        (ck / "grains.npz").write_bytes(data[: len(data) // 3])
    proc = granfe("restart", out, "--no-progress")
    assert proc.returncode == 1
    assert "no complete checkpoint" in proc.stderr and "does not match its sha256" in proc.stderr
    assert "Traceback" not in proc.stderr and "last_good" not in proc.stderr
    assert not (out / "last_good").exists()   # no "last good state" from an unsettled lattice


def test_second_run_into_the_same_directory_is_refused(tmp_path):
    out = tmp_path / "run"
    assert granfe("run", *PUNCH, "--out", out, "--no-progress").returncode == 0
    before = (out / "checkpoint" / "manifest.json").read_text()
    proc = granfe("run", *PUNCH, "--set", "penetrator.steps=2", "--out", out, "--no-progress")
    assert proc.returncode == 2 and "--overwrite" in proc.stderr and "Traceback" not in proc.stderr
    assert (out / "checkpoint" / "manifest.json").read_text() == before   # untouched
    proc = granfe("run", *PUNCH, "--set", "penetrator.steps=2", "--out", out, "--no-progress",
                  "--overwrite")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert checkpoint_step(out) == 2   # the old run's checkpoint of step 3 is gone
    rows = json.loads((out / "history.json").read_text())["steps"]
    assert [h["step"] for h in rows] == [1, 2]


def test_restart_refuses_another_scene_naming_the_keys(cpt_stopped, tmp_path):
    out = _copy(cpt_stopped, tmp_path)
    text = (out / "scene.toml").read_text()
    (out / "scene.toml").write_text(text.replace("friction = 0.5", "friction = 0.4")
                                    .replace("seed = 1", "seed = 2"))
    proc = granfe("restart", out, "--no-progress")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "grains.friction (0.5 in the checkpoint, 0.4 in scene.toml)" in proc.stderr
    assert "grains.seed" in proc.stderr


def test_restart_refuses_another_rank_count(cpt_stopped, tmp_path):
    out = _copy(cpt_stopped, tmp_path)
    proc = granfe("restart", out, "--no-progress", ranks=2)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "rank count (checkpoint written on 1 rank(s), restarted on 2" in proc.stderr


def test_punch_restart_keeps_frames_and_does_not_repeat_rows(tmp_path):
    """Killed after history.json got step 3 but before checkpoint 3 was complete."""
    out = tmp_path / "run"
    proc = granfe("run", *PUNCH, "--out", out, "--no-progress")
    assert proc.returncode == 0, proc.stderr[-3000:]
    frames = (out / "particles.pvd").read_text().count("<DataSet")
    assert frames == 3
    rows = json.loads((out / "history.json").read_text())["steps"]
    shutil.rmtree(out / "checkpoint")    # the checkpoint of step 3 never took its place
    proc = granfe("restart", out, "--no-progress")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "falling back to" in proc.stderr
    again = json.loads((out / "history.json").read_text())["steps"]
    assert [h["step"] for h in again] == [1, 2, 3]
    force = rows[-1]["punch_force"]
    assert abs(again[-1]["punch_force"] - force) <= 1e-8 * abs(force)
    assert (out / "particles.pvd").read_text().count("<DataSet") == frames


def test_punch_failure_at_step_1_restarts_after_the_fix(tmp_path):
    out = tmp_path / "run"
    proc = granfe("run", *PUNCH, "--out", out, "--no-progress", "--set", "solver.max_iterations=2",
                  "--set", "solver.cutbacks=0", "--set", "solver.tol=1e-14")
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert "step 1" in proc.stderr and f"granfe restart {out}" in proc.stderr
    assert checkpoint_step(out) == 0     # the initial state: the advice holds
    text = (out / "scene.toml").read_text()
    (out / "scene.toml").write_text(text.replace("max_iterations = 2", "max_iterations = 300")
                                    .replace("tol = 1e-14", "tol = 1e-08"))
    proc = granfe("restart", out, "--no-progress")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert [h["step"] for h in json.loads((out / "history.json").read_text())["steps"]] == [1, 2, 3]


def test_penetration_failure_before_any_checkpoint_does_not_advise_restart(tmp_path):
    out = tmp_path / "run"
    proc = granfe("run", *CPT, "--out", out, "--no-progress", "--set", "grains.settle_time=1e-4")
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert "set-up failed" in proc.stderr and "granfe restart" not in proc.stderr
    proc = granfe("restart", out, "--no-progress")
    assert proc.returncode == 1 and "no complete checkpoint" in proc.stderr


def test_quoted_name_is_written_so_that_the_run_restarts(tmp_path):
    out = tmp_path / "run"
    proc = granfe("run", *PUNCH, "--set", "scene.name=it's a \"test\"", "--out", out,
                  "--no-progress")
    assert proc.returncode == 0, proc.stderr[-3000:]
    proc = granfe("restart", out, "--no-progress")
    assert proc.returncode == 0 and "is complete (step 3 of 3)" in proc.stdout, proc.stderr[-3000:]


def test_sigterm_under_two_ranks_stops_every_rank_after_the_same_step(tmp_path):
    out = tmp_path / "run"
    proc = start("run", *PUNCH, "--set", "penetrator.steps=200", "--out", out, "--no-progress",
                 ranks=2)
    wait_for_checkpoint(proc, out, 2)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err[-3000:]
    step = checkpoint_step(out)
    assert f"continue with: mpiexec -n 2 granfe restart {out}" in err
    files = json.loads((out / "checkpoint" / "manifest.json").read_text())["files"]
    assert {"continuum_rank0_of2.npz", "continuum_rank1_of2.npz"} <= set(files)
    text = (out / "scene.toml").read_text().replace("steps = 200", f"steps = {step + 1}")
    (out / "scene.toml").write_text(text)
    proc = granfe("restart", out, "--no-progress", ranks=2)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert len(json.loads((out / "history.json").read_text())["steps"]) == step + 1


def test_restart_of_a_punch_run_as_a_penetration_run_is_refused(tmp_path):
    """scene.toml replaced by a valid scene of another kind: refused naming scene.kind."""
    from reliability_helpers import ROOT

    out = tmp_path / "run"
    assert granfe("run", *PUNCH, "--out", out, "--no-progress").returncode == 0
    shutil.copy(ROOT / "scenes/cpt_2d.toml", out / "scene.toml")
    proc = granfe("restart", out, "--no-progress")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    expected = "scene.kind ('bonded_punch' in the checkpoint, 'penetration' in scene.toml)"
    assert expected in proc.stderr
