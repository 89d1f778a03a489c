"""The pieces under the fault tests, serial and under mpiexec -n 2: atomic checkpoint
directories (:mod:`coupling.checkpoints`), run fingerprints (:mod:`coupling.rundir`) and the
signal flag every rank agrees on (:mod:`coupling.interrupts`)."""

import json
import os
import signal
from pathlib import Path

from mpi4py import MPI

import numpy as np
import pytest

from coupling.checkpoints import CheckpointError, find_checkpoint, validate, write_checkpoint
from coupling.interrupts import StopRequests
from coupling.rundir import differences, fingerprint
from coupling.scene import load_scene, parse_overrides


def _writer(value):
    def files(tmp: Path) -> list[str]:
        comm = MPI.COMM_WORLD
        name = f"part_rank{comm.rank}.npy"
        np.save(tmp / name, np.full(10, value + comm.rank))
        return [name]
    return files


@pytest.mark.mpi
def test_checkpoints_rotate_and_the_newest_valid_one_is_found(tmp_out):
    comm = MPI.COMM_WORLD
    base = Path(tmp_out) / "checkpoint"
    for step in (1, 2, 3):
        write_checkpoint(base, step, comm, _writer(step),
                         meta={"fingerprint": {"ranks": comm.size}})
    if comm.rank == 0:
        manifest = json.loads((base / "manifest.json").read_text())
        assert manifest["step"] == 3 and manifest["ranks"] == comm.size
        assert set(manifest["files"]) == {f"part_rank{r}.npy" for r in range(comm.size)}
        assert validate(base.parent / "checkpoint.prev")[0]["step"] == 2
        assert not list(base.parent.glob("checkpoint.tmp-*"))
        path, found, notes = find_checkpoint(base)
        assert path == base and found["step"] == 3 and notes == []
        # a corrupt file: the previous checkpoint, said so
        (base / "part_rank0.npy").write_bytes(b"\x93NUMPY garbage")
        path, found, notes = find_checkpoint(base)
        assert path.name == "checkpoint.prev" and found["step"] == 2
        assert any("part_rank0.npy does not match its sha256" in n for n in notes)
        assert any("falling back to" in n for n in notes)
        # a complete, newer checkpoint left under its temporary name wins
        (base.parent / "checkpoint.prev").rename(base.parent / "checkpoint.tmp-000007")
        data = json.loads((base.parent / "checkpoint.tmp-000007" / "manifest.json").read_text())
        data["step"] = 7
        (base.parent / "checkpoint.tmp-000007" / "manifest.json").write_text(json.dumps(data))
        assert find_checkpoint(base)[1]["step"] == 7
        (base.parent / "checkpoint.tmp-000007" / "manifest.json").unlink()
        with pytest.raises(CheckpointError, match="no complete checkpoint"):
            find_checkpoint(base)
    comm.barrier()


def test_fingerprint_names_the_keys_that_differ():
    a = load_scene(Path(__file__).parents[2] / "scenes/cpt_2d.toml")
    b = load_scene(Path(__file__).parents[2] / "scenes/cpt_2d.toml",
                   parse_overrides(["grains.friction=0.3", "output.frames=9", "scene.name=other"]))
    fa, fb = fingerprint(a, 1), fingerprint(b, 1)
    assert fa["sha256"] != fb["sha256"]
    # outputs and the name may change on restart
    assert [d.split(" ")[0] for d in differences(fa, fb)] == ["grains.friction"]
    assert differences(fa, fingerprint(a, 1)) == []
    assert "rank count" in differences(fa, fingerprint(a, 2))[0]
    # a JSON round trip (the manifest) keeps it equal
    assert differences(json.loads(json.dumps(fa)), fa) == []


@pytest.mark.mpi
def test_a_signal_on_one_rank_stops_every_rank():
    comm = MPI.COMM_WORLD
    before = signal.getsignal(signal.SIGTERM)
    with StopRequests(quiet=True) as stop:
        assert stop.requested(comm) == 0
        if comm.rank == 0:
            os.kill(os.getpid(), signal.SIGTERM)
        assert stop.requested(comm) == signal.SIGTERM
    assert signal.getsignal(signal.SIGTERM) == before


@pytest.mark.mpi
def test_a_full_disk_keeps_the_previous_checkpoint(tmp_out):
    """A write that fails on one rank (ENOSPC after part of a file) fails on every rank,
    leaves no partial directory and keeps the checkpoint already there."""
    import errno

    comm = MPI.COMM_WORLD
    base = Path(tmp_out) / "checkpoint"
    write_checkpoint(base, 1, comm, _writer(1))

    def full_disk(tmp: Path) -> list[str]:
        names = _writer(2)(tmp)
        if comm.rank == comm.size - 1:
            with open(tmp / names[0], "ab") as f:
                f.write(b"partial")
            raise OSError(errno.ENOSPC, "No space left on device")
        return names

    with pytest.raises(CheckpointError, match=r"No space left on device; the checkpoint of step 1 .* is kept"):
        write_checkpoint(base, 2, comm, full_disk)
    comm.barrier()
    if comm.rank == 0:
        assert validate(base)[0]["step"] == 1
        assert not list(base.parent.glob("checkpoint.tmp-*"))
        assert find_checkpoint(base)[1]["step"] == 1
    comm.barrier()


def test_too_little_free_disk_is_refused_before_writing(tmp_out, monkeypatch):
    """Outputs and checkpoints are not started with less free disk than twice the last
    checkpoint plus a reserve (ADIOS2 would abort the process midway); the message says how
    much is free and how to continue."""
    import shutil
    from collections import namedtuple

    from coupling import checkpoints

    comm = MPI.COMM_WORLD
    base = Path(tmp_out) / "checkpoint"
    write_checkpoint(base, 4, comm, _writer(4))
    checkpoints.ensure_free_space(tmp_out, comm)           # a real disk has room
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**9, 10**9 - 10**6, 10**6))
    with pytest.raises(checkpoints.DiskFull,
                       match=r"only 1 MB free .* the next frame needs about 64 MB: free disk "
                             r"space, then continue from the checkpoint of step 4"):
        checkpoints.ensure_free_space(tmp_out, comm, "frame")
    assert validate(base)[0]["step"] == 4
