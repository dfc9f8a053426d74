"""Map files (checkpoints) read safely: a file never runs code, and any file that is not a readable checkpoint of
this version is refused with one line that says what it is and what to do.

torch.save writes a zip archive: the tensors' bytes, and a pickle of the containers around them. Unpickling can
call any function a file names, so the pickle is read only by torch.load(weights_only=True), which rebuilds
tensors and plain values and refuses everything else. Before that, the file must be a zip archive whose entries
all pass their CRC check: a plain pickle (which torch would hand to its legacy reader), random bytes, a truncated
copy or flipped bits are refused without being unpickled at all.

A map that reads is then checked against the configuration and camera that would load it (check_compatible): every
load runs that check, and so does the ROS node's ~/load_map before it lets go of its current map.
"""
from __future__ import annotations

import dataclasses
import pickle
import zipfile
from pathlib import Path
from typing import Optional

import torch

from eslam_core.camera import Intrinsics
from eslam_core.config import Config, config_from_dict

ZIP_MAGIC = b"PK\x03\x04"
RERUN = "re-run `eslam run` (or save the map again) to make a new one"


class CheckpointError(ValueError):
    pass


def read_checkpoint(path: Path | str, version: int) -> dict:
    """The state dict in a checkpoint written by torch.save, if it is of `version`; CheckpointError otherwise."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path} (an `eslam run --out DIR` writes DIR/checkpoint.pt)")
    try:
        with path.open("rb") as f:
            magic = f.read(len(ZIP_MAGIC))
    except OSError as e:
        raise CheckpointError(f"{path} cannot be read ({e.strerror or type(e).__name__}); check its permissions") \
            from None
    if magic != ZIP_MAGIC:
        raise CheckpointError(f"{path} is not an ESLAM checkpoint (not an archive written by torch.save); "
                              f"give the checkpoint.pt of a run")
    try:
        with zipfile.ZipFile(path) as archive:
            damaged = archive.testzip()  # the first entry whose CRC does not match, None if all do
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as e:
        raise CheckpointError(f"{path} is damaged (truncated or corrupt archive: {_first_line(e)}); {RERUN}") from None
    if damaged is not None:
        raise CheckpointError(f"{path} is damaged (corrupt data in {damaged}); {RERUN}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        # torch's message suggests weights_only=False, i.e. running the file's code: never for a map file.
        raise CheckpointError(f"{path} is not an ESLAM checkpoint: it holds Python objects other than tensors "
                              f"and plain values, refused unread (a map file never runs code)") from None
    except (RuntimeError, EOFError, KeyError, ValueError, zipfile.BadZipFile) as e:
        raise CheckpointError(f"{path} is damaged (unreadable archive: {_first_line(e)}); {RERUN}") from None
    if not isinstance(state, dict) or "version" not in state:
        raise CheckpointError(f"{path} is not an ESLAM checkpoint (a torch file without a map inside)")
    if state["version"] != version:
        raise CheckpointError(f"{path} is a version {state['version']} checkpoint, this eslam reads version "
                              f"{version}; {RERUN} with this version")
    return state


# What SLAM.from_state_dict reads from a state (a file without them is not a map eslam wrote).
STATE_PARTS = {"config": dict, "intrinsics": dict, "map": dict, "trajectory": dict}
MAP_PARTS = ("extent", "field", "keyframes", "keyframes_made", "points_outside", "points_seen", "rng")
TRAJECTORY_PARTS = ("records", "keyframe_poses")


def check_compatible(state: dict, cfg: Config, intrinsics: Optional[Intrinsics], path: Path | str) -> None:
    """Every check a runtime's load of the map in `state` (read by read_checkpoint) makes, before any map is built:
    the state is complete, its config valid, its model settings and camera.image_scale are `cfg`'s and (if known)
    it was made for frames of `intrinsics`. CheckpointError, one line naming the problem and the fix, otherwise.
    Loading (slam.read_loadable) and the ROS node's ~/load_map, before it drops its map, both run this."""
    missing = [k for k, kind in STATE_PARTS.items() if not isinstance(state.get(k), kind)]
    missing += [f"map.{k}" for k in MAP_PARTS if "map" not in missing and k not in state["map"]]
    missing += [f"trajectory.{k}" for k in TRAJECTORY_PARTS if "trajectory" not in missing
                and k not in state["trajectory"]]
    if missing:
        raise CheckpointError(f"{path} is damaged (incomplete map: no {', '.join(missing)}); {RERUN}")
    try:
        saved = config_from_dict(state["config"], "its config", migrate=True)
        saved_intrinsics = Intrinsics(**state["intrinsics"])
    except (ValueError, TypeError) as e:
        raise CheckpointError(f"{path} is damaged (invalid settings inside: {_first_line(e)}); {RERUN}") from None
    if saved.model != cfg.model:
        other = [f"model.{f.name} is {getattr(saved.model, f.name)!r} in the map, {getattr(cfg.model, f.name)!r} "
                 f"in this config" for f in dataclasses.fields(saved.model)
                 if getattr(saved.model, f.name) != getattr(cfg.model, f.name)]
        more = f" (and {len(other) - 2} more)" if len(other) > 2 else ""
        raise CheckpointError(f"{path} was made with other model settings: {'; '.join(other[:2])}{more}; use the "
                              f"preset / config the map was made with ('{saved.name}') or make the map again")
    if saved.camera.image_scale != cfg.camera.image_scale:
        raise CheckpointError(f"{path} holds keyframes at camera.image_scale {saved.camera.image_scale}, this "
                              f"configuration has {cfg.camera.image_scale}; set camera.image_scale to "
                              f"{saved.camera.image_scale} to use this map")
    if saved.submaps.radius_m != cfg.submaps.radius_m:  # (each runtime builds its submaps by its own config)
        made = f"submaps of {saved.submaps.radius_m:g} m" if saved.submaps.radius_m > 0 else "one map"
        raise CheckpointError(f"{path} was made as {made}, this configuration has submaps.radius_m "
                              f"{cfg.submaps.radius_m:g}; set submaps.radius_m to {saved.submaps.radius_m:g} to use "
                              f"this map")
    if intrinsics is not None and saved_intrinsics != intrinsics:
        raise CheckpointError(f"{path} was made for camera {_camera(saved_intrinsics)}, these frames come from "
                              f"{_camera(intrinsics)}; use that camera, or make a map with this one")


def _camera(i: Intrinsics) -> str:
    return f"{i.width}x{i.height} fx={i.fx:.8g} fy={i.fy:.8g} cx={i.cx:.8g} cy={i.cy:.8g}"


def _first_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return text[0][:160] if text else type(e).__name__
