"""Map files are read safely: nothing in a file runs, and every bad file gets one line naming what it is."""
from __future__ import annotations

import builtins
import os
import pickle

import numpy as np
import pytest
import torch

from eslam_core.cli import main as eslam
from eslam_core.config import load_config
from eslam_core.datasets.synthetic import default_intrinsics
from eslam_core.outputs.export import load_checkpoint, save_checkpoint
from eslam_core.map_file import CheckpointError, read_checkpoint
from eslam_core.slam import CHECKPOINT_VERSION, SLAM


class CreatesFile:
    """Unpickling this calls open(marker, "w"): the file appears if, and only if, the pickle's code ran."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return builtins.open, (self.marker, "w")


def one_line_error(path, version=CHECKPOINT_VERSION) -> str:
    with pytest.raises(CheckpointError) as info:
        read_checkpoint(path, version)
    message = str(info.value)
    assert "\n" not in message and "weights_only" not in message and len(message) < 300, message
    assert str(path) in message
    return message


@pytest.fixture
def good(tmp_path):
    state = {"version": 7, "map": {"planes": torch.arange(1000.0).reshape(10, 100)}, "name": "room", "n": 3}
    path = tmp_path / "good.pt"
    torch.save(state, path)
    return path, state


def test_a_checkpoint_reads_back(good):
    path, state = good
    loaded = read_checkpoint(path, 7)
    assert loaded["name"] == "room" and loaded["n"] == 3
    assert torch.equal(loaded["map"]["planes"], state["map"]["planes"])


def test_an_empty_slam_state_round_trips(tmp_path):
    """save_checkpoint / load_checkpoint on a SLAM that has seen no frame yet (the cheapest real state)."""
    cfg = load_config("demo")
    path = save_checkpoint(SLAM(cfg, default_intrinsics(64, 48)), tmp_path / "checkpoint.pt")
    slam = load_checkpoint(path)
    assert slam.cfg.to_dict() == cfg.to_dict() and slam.input_intrinsics == default_intrinsics(64, 48)


def test_random_bytes_empty_and_text_files_are_not_checkpoints(tmp_path):
    files = {"random.pt": np.random.default_rng(0).bytes(5000), "empty.pt": b"", "notes.pt": b"hello map\n",
             "fake_zip.pt": b"PK\x03\x04" + np.random.default_rng(1).bytes(3000)}
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    for name in ("random.pt", "empty.pt", "notes.pt"):
        assert "not an ESLAM checkpoint" in one_line_error(tmp_path / name)
    assert "damaged" in one_line_error(tmp_path / "fake_zip.pt")


def test_truncated_and_bit_flipped_files_are_damaged(good, tmp_path):
    path, _ = good
    data = path.read_bytes()
    (tmp_path / "half.pt").write_bytes(data[: len(data) // 2])
    flipped = bytearray(data)
    planes_start = data.index(np.float32(500.0).tobytes())  # inside the tensor's bytes
    flipped[planes_start] ^= 0x01  # 500.0 -> 500.00006: torch.load alone would not notice
    (tmp_path / "flipped.pt").write_bytes(bytes(flipped))
    assert "damaged" in one_line_error(tmp_path / "half.pt")
    message = one_line_error(tmp_path / "flipped.pt")
    assert "damaged" in message and "corrupt data" in message


@pytest.mark.parametrize("container", ["pickle", "torch.save"])
def test_a_file_with_code_is_refused_and_the_code_never_runs(tmp_path, container):
    marker = tmp_path / "code_ran"
    payload = {"version": CHECKPOINT_VERSION, "map": CreatesFile(marker)}
    path = tmp_path / "evil.pt"
    if container == "pickle":
        with path.open("wb") as f:
            pickle.dump(payload, f)
    else:
        torch.save(payload, path)
    pickle.loads(pickle.dumps(CreatesFile(tmp_path / "probe")))  # the payload does work when unpickled...
    assert (tmp_path / "probe").exists()
    message = one_line_error(path)  # ... and reading the file as a map does not run it
    assert not marker.exists()
    assert "not an ESLAM checkpoint" in message
    with pytest.raises(CheckpointError):
        load_checkpoint(path)
    assert not marker.exists()


def test_other_versions_and_other_torch_files_are_named(tmp_path, good):
    path, _ = good
    message = one_line_error(path, version=8)
    assert "version 7" in message and "version 8" in message
    torch.save(torch.zeros(3), tmp_path / "tensor.pt")
    assert "without a map inside" in one_line_error(tmp_path / "tensor.pt")
    torch.save({"version": CHECKPOINT_VERSION, "map": {}}, tmp_path / "incomplete.pt")
    with pytest.raises(CheckpointError, match="damaged") as info:
        load_checkpoint(tmp_path / "incomplete.pt")
    assert "\n" not in str(info.value)


def test_eslam_mesh_reports_a_bad_file_in_one_line(tmp_path, capsys):
    bad = tmp_path / "checkpoint.pt"
    bad.write_bytes(os.urandom(2000))
    assert eslam(["mesh", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("eslam: error:") and "\n" not in err and "weights_only" not in err
    assert not list(tmp_path.glob("*.ply"))
    assert eslam(["mesh", str(tmp_path / "missing.pt")]) == 2
    assert "not found" in capsys.readouterr().err


def test_a_map_is_checked_against_the_loading_configuration_and_camera_in_one_place(tmp_path):
    """check_compatible: the checks a runtime's load makes (slam.read_loadable / loaded_slam), each refusal one line
    naming the setting; the camera is skipped when not known yet (the ROS node before its first frame)."""
    from eslam_core.map_file import check_compatible
    from eslam_core.slam import loaded_slam

    cfg, camera = load_config("fast"), default_intrinsics(64, 48)
    state = SLAM(cfg, camera).state_dict()
    path = tmp_path / "checkpoint.pt"
    check_compatible(state, cfg, camera, path)
    check_compatible(state, cfg, None, path)

    def refused(state, cfg, intrinsics=camera) -> str:
        with pytest.raises(CheckpointError) as info:
            check_compatible(state, cfg, intrinsics, path)
        message = str(info.value)
        assert "\n" not in message and str(path) in message and len(message) < 300, message
        return message

    other_preset = load_config("demo")  # the replica model: fine appearance planes of 0.03 m, not 0.06
    message = refused(state, other_preset)
    assert "model.fine_appearance_resolution is 0.06 in the map, 0.03 in this config" in message and "'fast'" in message
    assert "model.channels" in refused(state, load_config("fast", {"model": {"channels": 8}}))
    assert "camera.image_scale" in refused(state, load_config("fast", {"camera": {"image_scale": 0.5}}))
    message = refused(state, load_config("fast", {"submaps": {"radius_m": 2.0}}))
    assert "made as one map, this configuration has submaps.radius_m 2" in message and "radius_m to 0" in message
    message = refused(state, cfg, default_intrinsics(80, 60))
    assert "made for camera 64x48 fx=54.32522" in message and "come from 80x60 fx=67.906525" in message
    check_compatible(state, cfg, None, path)  # the camera unknown: that check waits, the others ran above
    assert "model.fine_appearance_resolution" in refused(state, other_preset, None)
    broken = dict(state, trajectory=None)
    assert "incomplete map: no trajectory" in refused(broken, cfg)
    broken = dict(state, map={k: v for k, v in state["map"].items() if k != "keyframes"})
    assert "incomplete map: no map.keyframes" in refused(broken, cfg)
    assert "invalid settings" in refused(dict(state, config={**state["config"], "model": {"channels": -1}}), cfg)

    # The loader runs the same check on the file (read_checkpoint first, then check_compatible).
    save_checkpoint(SLAM(cfg, camera), path)
    with pytest.raises(CheckpointError, match=r"model\.fine_appearance_resolution is 0\.06 in the map"):
        loaded_slam(path, other_preset, camera)
    assert loaded_slam(path, cfg, camera).cfg.model == cfg.model
