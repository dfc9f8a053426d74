"""Saving on a disk that fills up: every writer reports one line (file, space needed, what to do), leaves no
partial file, keeps an older file of the same name byte for byte, and the outputs that still fit are written.

The full disk is simulated where the bytes go out: torch.save writes part of the archive and fails as torch's zip
writer does (a RuntimeError without errno, free space 0), or a Python file's write() writes part and raises ENOSPC.
"""
from __future__ import annotations

import builtins
import errno
import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from eslam_core.cli import main
from eslam_core.config import load_config, save_config
from eslam_core.datasets.synthetic import default_intrinsics
from eslam_core.datasets.tum import read_tum
from eslam_core.trajectory import Trajectory
from eslam_core.atomic import OutputWriteError, write_atomic
from eslam_core.outputs.export import save_checkpoint, save_trajectory
from eslam_core.outputs.mesh import save_ply
from eslam_core.runtime.saving import SavingMixin
from eslam_core.slam import SLAM

HINT = "free space or choose another output folder"
TORCH_FULL = "[enforce fail at inline_container.cc:672] . unexpected pos 9792 vs 9684"
TINY_RUN = ["--config", "fast", "--frames", "0:2", "--no-mesh", "-q", "--set", "mapping.first_iterations=2",
            "--set", "mapping.iterations=1", "--set", "tracking.iterations=1"]


class FullDisk:
    """Writes to files whose name contains one of `names` fail part-way, as on a full disk."""

    def __init__(self, monkeypatch, names, free: int = 0):
        self.names, self.failures = tuple(names), 0
        real_save, real_open, real_usage = torch.save, builtins.open, shutil.disk_usage
        disk = self

        def save(obj, f, *args, **kwargs):
            if not disk.hits(f):
                return real_save(obj, f, *args, **kwargs)
            buffer = io.BytesIO()
            real_save(obj, buffer)
            with real_open(f, "wb") as part:  # the archive's start, then the disk is full
                part.write(buffer.getvalue()[:600])
            disk.failures += 1
            raise RuntimeError(TORCH_FULL)

        def open_(file, mode="r", *args, **kwargs):
            f = real_open(file, mode, *args, **kwargs)
            return PartWriter(f, disk) if "w" in mode and disk.hits(file) else f

        def usage(path):
            total, used, _ = real_usage(path)
            return shutil._ntuple_diskusage(total, used, free)

        monkeypatch.setattr(torch, "save", save)
        monkeypatch.setattr(builtins, "open", open_)
        monkeypatch.setattr(io, "open", open_)  # what pathlib's write_text / write_bytes call
        monkeypatch.setattr(shutil, "disk_usage", usage)

    def hits(self, file) -> bool:
        return isinstance(file, (str, Path)) and any(n in Path(file).name for n in self.names)


class PartWriter:
    """A file whose write() gets half of its bytes on the disk, then fails with ENOSPC."""

    def __init__(self, f, disk: FullDisk):
        self.f, self.disk = f, disk

    def write(self, data):
        self.f.write(data[: len(data) // 2])
        self.f.flush()
        self.disk.failures += 1
        raise OSError(errno.ENOSPC, "No space left on device")

    def __getattr__(self, name):
        return getattr(self.f, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.f.close()


def assert_one_line(message: str, path: Path, prefix: str = "") -> None:
    assert "\n" not in message and "Traceback" not in message, message
    assert message.startswith(prefix + "no space left on "), message
    assert f" writing {path} (" in message and " MB needed)" in message, message
    assert message.endswith(HINT), message


def files_in(folder: Path) -> set[str]:
    return {p.name for p in folder.iterdir()}


@pytest.fixture
def empty_slam():
    return SLAM(load_config("demo"), default_intrinsics(64, 48))


def a_trajectory(n: int = 5) -> Trajectory:
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, 0, 3] = np.arange(n) * 0.1
    return Trajectory(np.arange(n) * 0.5, poses)


def test_a_checkpoint_that_does_not_fit_is_one_line_and_the_older_one_is_intact(monkeypatch, tmp_path, empty_slam):
    old = tmp_path / "checkpoint.pt"
    old.write_bytes(b"PK\x03\x04 the checkpoint of an earlier save")
    before = old.read_bytes()
    disk = FullDisk(monkeypatch, ["checkpoint.pt"])
    with pytest.raises(OutputWriteError) as info:
        save_checkpoint(empty_slam, old)
    assert disk.failures == 1 and info.value.no_space
    assert_one_line(str(info.value), old)
    assert old.read_bytes() == before and files_in(tmp_path) == {"checkpoint.pt"}  # no partial file left


def test_torch_failing_with_room_left_is_not_called_a_full_disk(monkeypatch, tmp_path, empty_slam):
    """torch's error has no errno: the free space tells a full disk from another write failure."""
    FullDisk(monkeypatch, ["checkpoint.pt"], free=50 * 2**30)
    with pytest.raises(OutputWriteError) as info:
        save_checkpoint(empty_slam, tmp_path / "checkpoint.pt")
    message = str(info.value)
    assert "no space" not in message and not info.value.no_space and "\n" not in message
    assert str(tmp_path / "checkpoint.pt") in message and "inline_container" in message
    assert files_in(tmp_path) == set()


@pytest.mark.parametrize("name, write", [
    ("trajectory.txt", lambda path: save_trajectory(a_trajectory(), path)),
    ("mesh.ply", lambda path: save_ply(trimesh.creation.box(), path)),
    ("config.yaml", lambda path: save_config(load_config("demo"), path)),
    ("summary.json", lambda path: write_atomic(path, json.dumps({"frames": 3}))),
    ("checkpoint.pt", lambda path: SavedRuntime().save_checkpoint(path)),
    ("trajectory.txt", lambda path: SavedRuntime().save_trajectory(path)),
], ids=["trajectory", "mesh", "config", "summary", "runtime-checkpoint", "runtime-trajectory"])
def test_every_writer_fails_in_one_line_and_keeps_the_older_file(monkeypatch, tmp_path, name, write):
    old = tmp_path / name
    old.write_text("an earlier save\n")
    write(old.with_name("first_" + name))  # the same writer, on a disk with room
    disk = FullDisk(monkeypatch, [name])
    with pytest.raises(OutputWriteError) as info:
        write(old)
    assert disk.failures == 1
    assert_one_line(str(info.value), old)
    assert old.read_text() == "an earlier save\n"
    assert files_in(tmp_path) == {name, "first_" + name}


class SavedRuntime(SavingMixin):
    """The runtimes' save_* (what the node's services and shutdown call) over an empty map."""

    cfg = load_config("demo")

    def snapshot(self):
        return SLAM(self.cfg, default_intrinsics(64, 48))

    def trajectory(self):
        t = a_trajectory()
        return t.timestamps, t.poses


def test_eslam_run_writes_the_trajectory_when_the_checkpoint_does_not_fit(monkeypatch, room_sequence, tmp_path,
                                                                          capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "checkpoint.pt").write_bytes(b"an earlier run's checkpoint")
    disk = FullDisk(monkeypatch, ["checkpoint.pt"])
    code = main(["run", "--data", str(room_sequence.root), "--out", str(out), *TINY_RUN])
    err = capsys.readouterr().err
    assert code == 1 and disk.failures == 1 and "Traceback" not in err, err
    errors = [line for line in err.splitlines() if line.startswith("eslam: error:")]
    assert len(errors) == 1, err
    assert_one_line(errors[0], out / "checkpoint.pt", prefix="eslam: error: ")
    assert (out / "checkpoint.pt").read_bytes() == b"an earlier run's checkpoint"
    assert len(read_tum(out / "trajectory.txt").timestamps) == 2  # written first, before the checkpoint
    summary = json.loads((out / "summary.json").read_text())
    assert summary["not_written"] == [str(out / "checkpoint.pt")] and summary["n_frames"] == 2
    assert files_in(out) == {"checkpoint.pt", "config.yaml", "trajectory.txt", "pose_quality.csv", "summary.json"} | (
        {"groundtruth.txt"} & files_in(out))


def test_eslam_mesh_on_a_full_disk_is_one_line_and_keeps_the_older_mesh(monkeypatch, tmp_path, empty_slam, capsys):
    checkpoint = save_checkpoint(empty_slam, tmp_path / "checkpoint.pt")
    # A map with no frame has no surface: the mesh of a box stands for the extracted one (the writer is under test).
    monkeypatch.setattr("eslam_core.outputs.export.map_mesh", lambda slam, resolution: trimesh.creation.box())
    old = tmp_path / "meshes" / "mesh.ply"
    old.parent.mkdir()
    old.write_bytes(b"ply\nan earlier mesh\n")
    disk = FullDisk(monkeypatch, ["mesh.ply"])
    code = main(["mesh", str(checkpoint), "--out", str(old)])
    err = capsys.readouterr().err
    assert code == 1 and disk.failures == 1 and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1, err
    assert_one_line(err.strip(), old, prefix="eslam: error: ")
    assert old.read_bytes() == b"ply\nan earlier mesh\n" and files_in(old.parent) == {"mesh.ply"}


def test_the_nodes_trigger_save_reports_one_line_and_the_node_goes_on(monkeypatch, tmp_path):
    """What the node's ~/save_* services answer (RuntimeHost.save): one line naming the file, the older file of
    that name intact, and the node not failed."""
    pytest.importorskip("rclpy")
    import logging

    from eslam_ros.node_params import NodeSettings
    from eslam_ros.node_threads import LogThrottle
    from eslam_ros.runtime_host import RuntimeHost

    host = RuntimeHost(NodeSettings(output_dir=str(tmp_path)), load_config("fast"), logging.getLogger("test"),
                       LogThrottle(1.0), poses=None)
    host.runtime = SavedRuntime()  # what a running node holds, with an empty map
    old = tmp_path / "checkpoint.pt"
    old.write_bytes(b"saved before")
    disk = FullDisk(monkeypatch, ["checkpoint.pt"])
    saved, message = host.save("checkpoint.pt", lambda rt, p: rt.save_checkpoint(p))
    assert not saved and disk.failures == 1
    assert_one_line(message, old)
    assert old.read_bytes() == b"saved before" and host.failed is None
    saved, message = host.save("trajectory.txt", lambda rt, p: rt.save_trajectory(p))  # a small one still fits
    assert saved, message
    assert files_in(tmp_path) == {"checkpoint.pt", "trajectory.txt"}
