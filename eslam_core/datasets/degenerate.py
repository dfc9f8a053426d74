"""Synthetic views that geometry does not pin down: where a depth tracker can slide without its residuals noticing.

Each sequence starts on a well-constrained view (furniture), turns to a degenerate one and holds it for a stretch
while the camera creeps along the free direction (0.2 cm and up to 0.5 degrees per frame, as a hand-held camera
looking around), then turns back to the first view, which the map already holds:
- "two_planes": a ceiling meeting a wall, 0.6-0.85 m away; the translation along their edge (x) is free;
- "plane": a wall seen head-on from 0.8 m; the translation in the wall (x, z) and the turn about its normal are free;
- "corridor": a corridor looked along, its far end beyond the sensor's range; the translation along it (x) is free.
The surfaces of the degenerate views are what real ones look like: grey paint with a faint mottling, faint tile
seams, flush light panels (strong lines, mostly along the free direction), and the same Kinect-like sensor.

`generate_degenerate_scene` writes a TUM folder like `synthetic.generate_scene`, its scene.json saying which
frames are the degenerate stretch and along which world direction the view is free.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import numpy as np
import trimesh

from eslam_core.datasets.synthetic import (ROOM_SIZE, SensorModel, SyntheticScene, SyntheticSceneError, Texture,
                                           _assemble, _grid_box, _on_floor, _room_parts, default_intrinsics, look_at,
                                           write_tum_sequence)

VIEWS = ("two_planes", "plane", "corridor")
STEP_M = 0.002  # the camera's creep along the free direction, per frame
# Frames per phase: the constrained start, the turn to the degenerate view, the stretch, the turn back, the end.
PHASES = (40, 45, 70, 45, 30)

PAINT = Texture("mottled", (0.80, 0.80, 0.78), (0.74, 0.74, 0.73), 1.5, grain=0.02)
CEILING_TILES = Texture("tiles", (0.84, 0.84, 0.82), (0.78, 0.78, 0.77), 1.0 / 0.6, (0, 0, 1), grain=0.02)
CORRIDOR_FLOOR = Texture("mottled", (0.52, 0.50, 0.47), (0.49, 0.48, 0.45), 1.5, grain=0.02)
CORRIDOR = (10.0, 1.6, 2.2)  # x, y, z extent of the corridor, metres; x from -5 to 5


def _light_panels(centres, size) -> list[trimesh.Trimesh]:
    """Flush ceiling lights: thin boxes 2 mm under the ceiling (the depth sensor cannot tell them from it)."""
    return [_grid_box((size[0], size[1], 0.002), (x, y, z - 0.002)) for x, y, z in centres]


def build_plain_room(seed: int = 0) -> SyntheticScene:
    """The furnished room with a plain north wall and a tiled ceiling with two long light strips along x."""
    parts = _room_parts()
    height = ROOM_SIZE[2]
    parts["lights"] = _light_panels([(0.0, 1.15, height), (0.0, -0.6, height)], (3.0, 0.15))
    half = np.array(ROOM_SIZE[:2]) / 2.0
    bound = np.array([[-half[0], -half[1], 0.0], [half[0], half[1], height]])
    return _assemble(parts, bound, seed, {"wall_north": PAINT, "ceiling": CEILING_TILES})


def build_corridor(seed: int = 0) -> SyntheticScene:
    """A 10 m corridor (1.6 m wide, 2.2 m high) of plain walls, a tiled ceiling with a light panel every 2.5 m, and
    a cabinet and two boxes against its south wall near the west end."""
    length, width, height = CORRIDOR
    gap = 0.01
    parts: dict[str, list[trimesh.Trimesh]] = {
        "room": [_grid_box((length, width, height), (0.0, 0.0, height / 2.0), inward=True)],
        "cabinet": [_on_floor((0.5, 0.45, 0.9), -3.0, -width / 2 + gap + 0.225)],
        "box_red": [_on_floor((0.3, 0.25, 0.2), -3.0, -width / 2 + gap + 0.125, z0=0.9)],
        "box_blue": [_on_floor((0.35, 0.35, 0.5), -2.4, -width / 2 + gap + 0.2, yaw_deg=20.0)],
        "lights": _light_panels([(x, 0.0, height) for x in np.arange(-5.0 + 1.25, 5.0, 2.5)], (1.2, 0.2)),
    }
    bound = np.array([[-length / 2, -width / 2, 0.0], [length / 2, width / 2, height]])
    plain = {"wall_west": PAINT, "wall_east": PAINT, "wall_south": PAINT, "wall_north": PAINT,
             "ceiling": CEILING_TILES, "floor": CORRIDOR_FLOOR}
    return _assemble(parts, bound, seed, plain)


def _ease(s: np.ndarray) -> np.ndarray:
    """0 -> 1 with zero speed at both ends (a camera starts and ends a turn smoothly)."""
    return 0.5 - 0.5 * np.cos(np.pi * np.clip(s, 0.0, 1.0))


def _views(view: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(eye, target) of the constrained view and of the degenerate one at x = 0 of the walk, and the free
    direction (world, unit)."""
    if view == "two_planes":  # the ceiling meets the north wall at y = 1.5, z = 2.6
        return (np.array([-0.2, 0.35, 1.6]), np.array([-0.2, 1.5, 0.5]), np.array([-0.2, 0.9, 2.0]),
                np.array([-0.2, 1.5, 2.6]), np.array([1.0, 0.0, 0.0]))
    if view == "plane":  # the north wall, head-on, between the sofa's back and the ceiling
        return (np.array([-0.2, 0.35, 1.6]), np.array([-0.2, 1.5, 0.5]), np.array([-0.2, 0.7, 1.9]),
                np.array([-0.2, 1.5, 1.9]), np.array([1.0, 0.0, 0.0]))
    if view == "corridor":  # the cabinet at x = -3 on the south wall, then east along the corridor
        return (np.array([-3.6, 0.25, 1.5]), np.array([-2.8, -0.8, 0.6]), np.array([-3.6, 0.1, 1.5]),
                np.array([5.0, -0.1, 1.5]), np.array([1.0, 0.0, 0.0]))
    raise SyntheticSceneError(f"unknown degenerate view {view!r}: use one of {VIEWS}")


def degenerate_trajectory(view: str, phases: tuple[int, ...] = PHASES, seed: int = 0
                          ) -> tuple[np.ndarray, range, np.ndarray]:
    """(N, 4, 4) camera-to-world poses, the frames of the degenerate stretch and its free direction (world)."""
    if len(phases) != 5 or min(phases) < 1:
        raise SyntheticSceneError(f"phases are five frame counts >= 1 (start, turn, stretch, turn back, end), got "
                                  f"{phases}")
    eye_a, target_a, eye_b, target_b, free = _views(view)
    n = sum(phases)
    k = np.arange(n)
    start, turn, stretch, back, _ = phases
    # How far into the degenerate view each frame is (0: the constrained view, 1: the degenerate one).
    s = np.where(k < start, 0.0, _ease((k - start) / turn))
    s = np.where(k >= start + turn + stretch, 1.0 - _ease((k - start - turn - stretch) / back), s)
    rng = np.random.default_rng([seed, 0xDE6])
    phase = rng.uniform(0.0, 2.0 * np.pi, 3)
    walk = STEP_M * k
    sway = np.stack([np.zeros(n), 0.003 * np.sin(2 * np.pi * k / 45 + phase[0]),
                     0.003 * np.sin(2 * np.pi * k / 37 + phase[1])], 1)
    eye = (1 - s)[:, None] * eye_a + s[:, None] * eye_b + walk[:, None] * free + sway
    # A slow pan about the view (about +-5 degrees, at most 0.5 degrees a frame): the camera looks around.
    distance = np.linalg.norm(target_b - eye_b)
    pan = 0.09 * distance * np.sin(2 * np.pi * k / 110 + phase[2])
    target = (1 - s)[:, None] * target_a + s[:, None] * target_b + (walk + pan)[:, None] * free
    poses = np.stack([look_at(eye[i], target[i]) for i in range(n)])
    return poses, range(start + turn, start + turn + stretch), free


def generate_degenerate_scene(out_dir, view: str, width: int = 160, height: int = 120, seed: int = 0,
                              phases: tuple[int, ...] = PHASES, sensor: Optional[SensorModel] = None) -> Path:
    """Render a degenerate-view sequence into the TUM folder `out_dir` (new or empty); returns its path."""
    poses, stretch, free = degenerate_trajectory(view, phases, seed)
    scene = build_corridor(seed) if view == "corridor" else build_plain_room(seed)
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise SyntheticSceneError(f"{out} already exists and is not an empty folder: delete it or pick a new one")
    path = write_tum_sequence(out, scene, poses, default_intrinsics(width, height),
                              SensorModel() if sensor is None else sensor, seed)
    settings = json.loads((path / "scene.json").read_text())
    settings["degenerate"] = {"view": view, "stretch": [stretch.start, stretch.stop], "free_direction":
                              free.tolist(), "step_m": STEP_M}
    (path / "scene.json").write_text(json.dumps(settings, indent=2) + "\n")
    return path


def stretch_of(path) -> tuple[range, np.ndarray]:
    """The degenerate stretch (frame indices) and its free direction, read from a generated folder."""
    info = json.loads((Path(path) / "scene.json").read_text())["degenerate"]
    return range(*info["stretch"]), np.asarray(info["free_direction"])

