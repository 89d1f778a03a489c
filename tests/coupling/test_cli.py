"""The granfe command: check, run (outputs, checkpoint), restart, failure with last good state."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
GRANFE = Path(sys.executable).parent / "granfe"
SMALL = ["--set", "geometry.width=0.2", "--set", "geometry.height=0.1", "--set", "geometry.element_size=0.02",
         "--set", "particles.radius=0.004", "--set", "window.half_width=0.06", "--set", "window.depth=0.05",
         "--set", "penetrator.steps=2", "--set", "output.png=false"]


def granfe(*args):
    cmd = [str(GRANFE)] if GRANFE.exists() else [sys.executable, "-m", "coupling.cli"]
    return subprocess.run(cmd + list(args), cwd=ROOT, capture_output=True, text=True, timeout=600)


def test_check_summarises():
    proc = granfe("check", "scenes/punch_2d.toml")
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    assert info["valid"] and info["fe_dofs"] > 0 and info["grains_in_window_and_ghost_band"] > 0


def test_check_names_bad_key():
    proc = granfe("check", "scenes/punch_2d.toml", "--set", "window.widht=0.1")
    assert proc.returncode == 2
    assert "unknown key window.widht" in proc.stderr


@pytest.mark.slow
def test_run_then_restart_reproduces(tmp_path):
    out = tmp_path / "run"
    proc = granfe("run", "scenes/punch_2d.toml", "--out", str(out), "--no-progress", *SMALL)
    assert proc.returncode == 0, proc.stderr[-3000:]
    history = json.loads((out / "history.json").read_text())["steps"]
    assert [h["step"] for h in history] == [1, 2]
    # linear problem: force proportional to settlement
    assert abs(history[1]["punch_force"] / history[0]["punch_force"] - 2.0) < 1e-6
    assert (out / "particles.pvd").exists() and list(out.glob("particles_*.vtu"))
    assert list(out.glob("continuum*_fields.bp"))
    # rewind the checkpoint to step 1 and restart: step 2 is recomputed from the saved state
    state = out / "checkpoint" / "state.json"
    json.loads(state.read_text())
    state.write_text(json.dumps({"step": 1}))
    history_file = out / "history.json"
    data = json.loads(history_file.read_text())
    data["steps"] = data["steps"][:1]
    history_file.write_text(json.dumps(data))
    proc = granfe("restart", str(out), "--no-progress")
    assert proc.returncode == 0, proc.stderr[-3000:]
    again = json.loads(history_file.read_text())["steps"]
    assert [h["step"] for h in again] == [1, 2]
    assert abs(again[1]["punch_force"] - history[1]["punch_force"]) < 1e-6 * abs(history[1]["punch_force"])
    # a complete run: restart says so and leaves it alone
    proc = granfe("restart", str(out), "--no-progress")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "is complete (step 2 of 2); nothing to restart" in proc.stdout
    assert json.loads(history_file.read_text())["steps"] == again


@pytest.mark.slow
def test_failing_step_stops_with_last_good_state(tmp_path):
    out = tmp_path / "fail"
    proc = granfe("run", "scenes/punch_2d.toml", "--out", str(out), "--no-progress", *SMALL,
                  "--set", "solver.max_iterations=2", "--set", "solver.cutbacks=1", "--set", "solver.tol=1e-14")
    assert proc.returncode == 1
    assert "failed after 1 cut-backs" in proc.stderr and "Last good state" in proc.stderr
    assert list((out / "checkpoint").glob("continuum_rank0_of1.npz"))


@pytest.mark.slow
def test_run_two_ranks_equals_serial(tmp_path):
    mpiexec = Path(sys.executable).parent / "mpiexec"
    if not mpiexec.exists():
        pytest.skip("no mpiexec in the environment")
    forces = []
    for ranks in (1, 2):
        out = tmp_path / f"r{ranks}"
        cmd = [str(mpiexec), "-n", str(ranks), sys.executable, "-m", "coupling.cli", "run",
               "scenes/punch_2d.toml", "--out", str(out), "--no-progress", *SMALL,
               "--set", "solver.tol=1e-12", "--set", "output.fields=false", "--set", "output.particles=false"]
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600,
                              env={**__import__("os").environ, "NUMBA_NUM_THREADS": "1"})
        assert proc.returncode == 0, proc.stderr[-3000:]
        forces.append([h["punch_force"] for h in json.loads((out / "history.json").read_text())["steps"]])
    assert abs(forces[0][-1] - forces[1][-1]) < 1e-10 * abs(forces[0][-1])


@pytest.mark.slow
def test_penetration_scene_runs(tmp_path):
    out = tmp_path / "cpt"
    proc = granfe("run", "scenes/cpt_2d.toml", "--out", str(out), "--no-progress",
                  "--set", "grains.settle_time=0.04", "--set", "penetrator.depth=0.004",
                  "--set", "penetrator.velocity=0.4", "--set", "output.png=false",
                  "--set", "output.frames=2")
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads((out / "results.json").read_text())
    assert results["grains"] > 500 and len(results["history"]) > 3
    assert (out / "grains.pvd").exists() and (out / "tip_resistance.csv").exists()
    # the physics of q_c is tested in test_flagship.py; here: the CSV holds what results.json
    # holds, every FE step, at increasing depth
    import csv

    with open(out / "tip_resistance.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(results["history"])
    for row, h in zip(rows, results["history"], strict=True):
        assert float(row["q_c"]) == pytest.approx(h["q_c"], rel=1e-12, abs=1e-9)
    depths = [h["depth"] for h in results["history"]]
    assert np.all(np.diff(depths) > 0)


TINY_3D = ["--set", "chamber.width=0.14", "--set", "chamber.depth=0.08",
           "--set", "chamber.element_size_window=0.01", "--set", "chamber.element_size_far=0.05",
           "--set", "window.half_width=0.02", "--set", "window.depth=0.04", "--set", "window.ghost_width=1.5",
           "--set", "window.handshake=1.0", "--set", "grains.radius=3.5e-3", "--set", "grains.settle_time=0.04",
           "--set", "penetrator.radius=0.008", "--set", "penetrator.depth=0.008",
           "--set", "penetrator.velocity=0.8", "--set", "coupling.substeps=20",
           "--set", "output.checkpoint_every=10", "--set", "output.frames=1", "--set", "output.png=false",
           "--set", "output.fields=false"]


@pytest.mark.slow
def test_3d_penetration_restart_continues_the_run(tmp_path):
    """granfe run (16 steps, checkpoint at step 10) then granfe restart from step 10: the
    restarted steps equal the uninterrupted ones to round-off."""
    out = tmp_path / "cpt3d"
    proc = granfe("run", "scenes/cpt_3d.toml", "--out", str(out), "--no-progress", *TINY_3D)
    assert proc.returncode == 0, proc.stderr[-3000:]
    first = json.loads((out / "results.json").read_text())
    assert first["grains"] > 300 and first["parameters"]["dim"] == 3
    assert json.loads((out / "checkpoint" / "state.json").read_text())["step"] == 10
    proc = granfe("restart", str(out), "--no-progress")
    assert proc.returncode == 0, proc.stderr[-3000:]
    again = json.loads((out / "results.json").read_text())
    assert again["restarted_from_step"] == 10
    a = [(h["q_c"], h["depth"]) for h in first["history"]]
    b = [(h["q_c"], h["depth"]) for h in again["history"]]
    assert len(a) == len(b) > 10
    scale = max(abs(q) for q, _ in a)
    assert scale > 0 and all(abs(x[0] - y[0]) <= 1e-10 * scale and x[1] == y[1] for x, y in zip(a, b, strict=False))
    # one series of grains across the restart: its frame at step 16 written again, not twice
    assert (out / "grains.pvd").read_text().count("<DataSet") == 1


CPTU_SMALL = [a for kv in ("chamber.width=0.16", "chamber.depth=0.12", "chamber.element_size_window=0.008",
                            "chamber.element_size_far=0.03", "grains.radius=1.5e-3", "grains.jitter=0.4",
                            "grains.friction=0.8", "grains.settle_time=0.15", "window.half_width=0.025",
                            "window.depth=0.045", "window.handshake=1.0", "penetrator.radius=0.0045",
                            "penetrator.depth=0.006", "coupling.substeps=50", "coupling.dt_factor=4.0",
                            "fluid.permeability=1e-11", "fluid.compressibility=1e-6",
                            "fluid.saturation_time=0.02", "fluid.every=10", "output.checkpoint_every=3",
                            "output.png=false", "output.frames=1", "output.fields=false")
              for a in ("--set", kv)]


def test_saturated_penetration_restart_repeats_the_run(tmp_path):
    """granfe run of the CPTu scene (small, checkpoints every 3 FE steps) then granfe
    restart from the last checkpoint: q_c and u2 of the restarted steps equal the
    uninterrupted run's to the bit (the fluid's state is in the checkpoint)."""
    out = tmp_path / "cptu"
    proc = granfe("run", "scenes/cptu_2d.toml", "--out", str(out), "--no-progress", *CPTU_SMALL)
    assert proc.returncode == 0, proc.stderr[-3000:]
    first = json.loads((out / "results.json").read_text())
    step = json.loads((out / "checkpoint" / "state.json").read_text())["step"]
    assert 0 < step < len(first["history"]) and "fluid" in first
    proc = granfe("restart", str(out), "--no-progress")
    assert proc.returncode == 0, proc.stderr[-3000:]
    again = json.loads((out / "results.json").read_text())
    assert again["restarted_from_step"] == step
    a = [(h["q_c"], h["u2"]) for h in first["history"]]
    assert a == [(h["q_c"], h["u2"]) for h in again["history"]] and any(q for q, _ in a)


def test_restart_without_checkpoint_is_named(tmp_path):
    (tmp_path / "scene.toml").write_text(open(ROOT / "scenes/cpt_3d.toml").read())
    proc = granfe("restart", str(tmp_path), "--no-progress")
    assert proc.returncode == 1
    assert "no complete checkpoint" in proc.stderr


def test_follow_scene_moves_the_window(tmp_path):
    """``[follow]``: the window of scenes/cpt_2d_follow.toml moves in a short push (its first
    move before the push: 50 mm is less than the trigger distance); the moves are in
    results.json; a follow scene asking for checkpoints, or too shallow a
    chamber for its push, is refused naming the key."""
    out = tmp_path / "follow"
    proc = granfe("run", "scenes/cpt_2d_follow.toml", "--out", str(out), "--no-progress",
                  "--set", "grains.settle_time=0.04", "--set", "penetrator.depth=0.012",
                  "--set", "follow.settle_steps=1000", "--set", "output.png=false",
                  "--set", "output.frames=1", "--set", "output.fields=false")
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads((out / "results.json").read_text())
    moves = results["window_moves"]
    assert len(moves) >= 1 and all(m["created"] > 0 for m in moves)
    assert results["history"][-1]["depth"] >= 0.012 - 1e-9
    assert results["history"][-1]["grains"] > results["history"][0]["grains"]
    bad = granfe("check", "scenes/cpt_2d_follow.toml", "--set", "output.checkpoint_every=5")
    assert bad.returncode != 0 and "output.checkpoint_every" in bad.stderr
    deep = granfe("check", "scenes/cpt_2d_follow.toml", "--set", "penetrator.depth=0.15")
    assert deep.returncode != 0 and "chamber.depth" in deep.stderr
