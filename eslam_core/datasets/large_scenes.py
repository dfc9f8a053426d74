"""Synthetic spaces larger than a room, for the submap and loop-closure benchmark (bench/submaps.py): where one set
of feature planes aliases (two storeys share every xy projection) and where drift shows (a walk that comes back).

- "flat": a 12 x 10 m flat, a hallway along x between three rooms on each side, each room furnished like the
  synthetic room; the camera walks from the north-west room along the hallway into the south-east room, round it,
  and back to where it started.
- "corridor_loop": a ring of corridors (1.6 m wide) round a 6.8 x 4.8 m block, 30 m along its centre line, with
  furniture and pictures along its walls; the camera walks it once and on to where it began.
- "two_storey": two rooms of the same 6 x 4 m footprint stacked 2.9 m apart, a stair between them through an
  opening in the slab; the camera walks the ground floor, climbs, and walks the upper floor.

Walls are textured as the synthetic room's and every few metres something stands against them: a long view of
plain wall is a degenerate view (datasets/degenerate.py), which is not what these scenes measure. The camera walks
`step_m` a frame (2.5 cm: 0.75 m/s at 30 Hz) at eye height, looking ahead and panning +-25 degrees to either side.

`generate_large_scene` writes a TUM folder as `synthetic.generate_scene` does, with the true mesh (mesh.ply).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import trimesh

from eslam_core.datasets.synthetic import (SensorModel, SyntheticScene, SyntheticSceneError, _assemble, _grid_box,
                                           _room_parts, default_intrinsics, look_at, write_tum_sequence)

WALL_T = 0.02  # wall thickness, metres (thin: the synthetic room's furniture stands against its walls)
DOOR_W, DOOR_H = 1.0, 2.1
STOREY_H = 2.6  # floor to ceiling
SLAB_T = 0.3  # between two storeys
EYE_H = 1.5
SCENES = ("flat", "corridor_loop", "two_storey")


def _slab(x0: float, x1: float, y0: float, y1: float, z0: float, z1: float) -> trimesh.Trimesh:
    """An axis-aligned box between the given corners."""
    return _grid_box((x1 - x0, y1 - y0, z1 - z0), ((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2))


def _wall(a: tuple[float, float], b: tuple[float, float], z0: float, doors: tuple[float, ...] = (),
          height: float = STOREY_H) -> list[trimesh.Trimesh]:
    """A wall from a to b (along x or along y) standing on z0, with a door (DOOR_W wide, DOOR_H high) centred at
    each distance along it in `doors`."""
    (xa, ya), (xb, yb) = a, b
    along_x = ya == yb
    if not along_x and xa != xb:
        raise SyntheticSceneError(f"walls run along x or y: {a} -> {b}")
    lo, hi = (min(xa, xb), max(xa, xb)) if along_x else (min(ya, yb), max(ya, yb))
    cuts = [lo] + [c for d in sorted(doors) for c in (lo + d - DOOR_W / 2, lo + d + DOOR_W / 2)] + [hi]
    pieces = []
    for i in range(0, len(cuts), 2):  # solid from each cut to the next door
        s0, s1 = cuts[i], cuts[i + 1]
        if s1 - s0 > 1e-6:
            pieces.append((s0, s1, z0, z0 + height))
    for d in doors:  # the lintel over each door
        pieces.append((lo + d - DOOR_W / 2, lo + d + DOOR_W / 2, z0 + DOOR_H, z0 + height))
    half = WALL_T / 2
    return [_slab(s0, s1, ya - half, ya + half, h0, h1) if along_x else _slab(xa - half, xa + half, s0, s1, h0, h1)
            for s0, s1, h0, h1 in pieces]


def _furnished(cx: float, cy: float, z0: float = 0.0, yaw_deg: float = 0.0,
               only: Optional[tuple[str, ...]] = None) -> dict[str, list[trimesh.Trimesh]]:
    """The synthetic room's furniture (not its shell), turned by `yaw_deg` and moved to (cx, cy, z0)."""
    move = trimesh.transformations.rotation_matrix(np.radians(yaw_deg), [0, 0, 1])
    move[:3, 3] = [cx, cy, z0]
    return {name: [p.copy().apply_transform(move) for p in pieces] for name, pieces in _room_parts().items()
            if name != "room" and (only is None or name in only)}


def _merge(*groups: dict) -> dict[str, list[trimesh.Trimesh]]:
    out: dict[str, list[trimesh.Trimesh]] = {}
    for group in groups:
        for name, pieces in group.items():
            out.setdefault(name, []).extend(pieces)
    return out


def _along_wall(points: list[tuple[float, float, float]], z0: float = 0.0) -> dict[str, list[trimesh.Trimesh]]:
    """A cabinet, a box on it and a picture above it at each (x, y, yaw) (yaw: the way the wall faces)."""
    out: dict[str, list[trimesh.Trimesh]] = {}
    for k, (x, y, yaw) in enumerate(points):
        move = trimesh.transformations.rotation_matrix(np.radians(yaw), [0, 0, 1])
        move[:3, 3] = [x, y, z0]
        height = 0.6 + 0.3 * (k % 3)
        pieces = {"cabinet": _slab(-0.4, 0.4, 0.0, 0.45, 0.0, height),
                  ("box_red" if k % 2 else "box_blue"): _slab(-0.25 + 0.1 * (k % 3), 0.05 + 0.1 * (k % 3), 0.05,
                                                              0.35, height, height + 0.15 + 0.1 * (k % 2)),
                  "painting": _slab(-0.5 + 0.2 * (k % 2), 0.4, 0.0, 0.03, 1.3, 1.9)}
        for name, piece in pieces.items():
            out.setdefault(name, []).append(piece.apply_transform(move))
    return out


def build_flat(seed: int = 0) -> SyntheticScene:
    """12 x 10 m: a 2 m hallway along x (y from -1 to 1) between three 4 x 4 m rooms north and three south."""
    parts: dict[str, list[trimesh.Trimesh]] = {
        "floor": [_slab(-6, 6, -5, 5, -0.05, 0.0)], "ceiling": [_slab(-6, 6, -5, 5, STOREY_H, STOREY_H + 0.05)],
        "wall_west": _wall((-6, -5), (-6, 5), 0.0), "wall_east": _wall((6, -5), (6, 5), 0.0),
        "wall_north": _wall((-6, 5), (6, 5), 0.0) + _wall((-6, 1), (6, 1), 0.0, doors=(2.0, 6.0, 10.0)),
        "wall_south": _wall((-6, -5), (6, -5), 0.0) + _wall((-6, -1), (6, -1), 0.0, doors=(2.0, 6.0, 10.0)),
    }
    for x in (-2.0, 2.0):  # the walls between the rooms
        parts["wall_west"] += _wall((x, 1), (x, 5), 0.0) + _wall((x, -5), (x, -1), 0.0)
    # (The room's painting hangs on a wall 1.5 m from its centre; these rooms are 4 m deep: it is left out.)
    furniture = ("table_top", "table_legs", "box_red", "box_blue", "cabinet", "sofa", "lamp")
    rooms = [_furnished(cx, cy, yaw_deg=yaw, only=furniture) for cx, cy, yaw in
             ((-4, 3.4, 0), (0, 3.4, 0), (4, 3.4, 0), (-4, -3.4, 180), (0, -3.4, 180), (4, -3.4, 180))]
    m = WALL_T / 2  # (between the doors, which are at x = -4, 0 and 4)
    hallway = _along_wall([(-2.0, 1 - m, 180), (2.2, 1 - m, 180), (-5.2, -1 + m, 0), (-1.8, -1 + m, 0),
                           (5.2, -1 + m, 0)])
    bound = np.array([[-6.0, -5.0, 0.0], [6.0, 5.0, STOREY_H]])
    return _assemble(_merge(parts, *rooms, hallway), bound, seed)


def flat_path() -> list[tuple[float, float, float]]:
    """From the north-west room along the hallway into the south-east room, round it and back (x, y, floor z)."""
    out = [(-4.5, 2.5, 0), (-4.0, 1.6, 0), (-4.0, 0.0, 0), (4.0, 0.0, 0), (4.0, -1.6, 0), (4.6, -2.6, 0),
           (3.4, -2.6, 0), (4.0, -1.6, 0), (4.0, 0.0, 0), (-4.0, 0.0, 0), (-4.0, 1.6, 0), (-4.5, 2.5, 0)]
    return out


CORRIDOR_W = 1.6
LOOP_OUTER = (10.0, 8.0)  # x, y extent of the ring's outer walls


def build_corridor_loop(seed: int = 0) -> SyntheticScene:
    ox, oy = LOOP_OUTER[0] / 2, LOOP_OUTER[1] / 2
    ix, iy = ox - CORRIDOR_W, oy - CORRIDOR_W
    parts: dict[str, list[trimesh.Trimesh]] = {
        "floor": [_slab(-ox, ox, -oy, oy, -0.05, 0.0)], "ceiling": [_slab(-ox, ox, -oy, oy, STOREY_H,
                                                                           STOREY_H + 0.05)],
        "wall_west": _wall((-ox, -oy), (-ox, oy), 0.0) + _wall((ix, -iy), (ix, iy), 0.0),
        "wall_east": _wall((ox, -oy), (ox, oy), 0.0) + _wall((-ix, -iy), (-ix, iy), 0.0),
        "wall_north": _wall((-ox, oy), (ox, oy), 0.0) + _wall((-ix, -iy), (ix, -iy), 0.0),
        "wall_south": _wall((-ox, -oy), (ox, -oy), 0.0) + _wall((-ix, iy), (ix, iy), 0.0),
    }
    # Something against the outer or inner wall every 2-3 m (facing into the corridor).
    m = WALL_T / 2
    props = _along_wall([(x, oy - m, 180) for x in (-3.0, 0.5, 3.5)] + [(x, -oy + m, 0) for x in (-2.0, 2.5)] +
                        [(ox - m, y, 90) for y in (-1.5, 1.8)] + [(-ox + m, y, -90) for y in (-2.0, 1.0)] +
                        [(x, iy + m, 0) for x in (-1.5, 2.0)] + [(x, -iy - m, 180) for x in (-2.5, 1.0)] +
                        [(ix + m, 0.0, -90), (-ix - m, 0.5, 90)])
    bound = np.array([[-ox, -oy, 0.0], [ox, oy, STOREY_H]])
    return _assemble(_merge(parts, props), bound, seed)


def corridor_loop_path() -> list[tuple[float, float, float]]:
    """Once round the ring along its centre line (counter-clockwise from the south-west), and 3 m on."""
    cx, cy = LOOP_OUTER[0] / 2 - CORRIDOR_W / 2, LOOP_OUTER[1] / 2 - CORRIDOR_W / 2
    return [(-cx, -cy + 1.0, 0), (-cx, -cy, 0), (cx, -cy, 0), (cx, cy, 0), (-cx, cy, 0), (-cx, -cy, 0),
            (-cx + 3.0, -cy, 0)]


TWO_STOREY = (6.0, 4.0)  # x, y footprint of both storeys
STAIR = (-0.6, 2.4, -1.9, -0.9)  # x0, x1, y0, y1 of the stair (rising along +x), south side of the footprint


def build_two_storey(seed: int = 0) -> SyntheticScene:
    hx, hy = TWO_STOREY[0] / 2, TWO_STOREY[1] / 2
    upper = STOREY_H + SLAB_T
    x0, x1, y0, y1 = STAIR
    parts: dict[str, list[trimesh.Trimesh]] = {
        "floor": [_slab(-hx, hx, -hy, hy, -0.05, 0.0),
                  # the slab between the storeys, with an opening over the stair
                  _slab(-hx, x0, -hy, hy, STOREY_H, upper), _slab(x1, hx, -hy, hy, STOREY_H, upper),
                  _slab(x0, x1, y1, hy, STOREY_H, upper)],
        "ceiling": [_slab(-hx, hx, -hy, hy, upper + STOREY_H, upper + STOREY_H + 0.05)],
        "wall_west": _wall((-hx, -hy), (-hx, hy), 0.0, height=2 * STOREY_H + SLAB_T),
        "wall_east": _wall((hx, -hy), (hx, hy), 0.0, height=2 * STOREY_H + SLAB_T),
        "wall_north": _wall((-hx, hy), (hx, hy), 0.0, height=2 * STOREY_H + SLAB_T),
        "wall_south": _wall((-hx, -hy), (hx, -hy), 0.0, height=2 * STOREY_H + SLAB_T),
    }
    steps = 12
    rise, run = upper / steps, (x1 - x0) / steps
    parts["table_legs"] = [_slab(x0 + k * run, x1, y0, y1, k * rise, (k + 1) * rise) for k in range(steps)]
    # The same furniture on both storeys, turned differently: the planes' xy projections of the two overlap.
    rooms = [_furnished(-1.0, 0.2, only=("table_top", "table_legs", "box_red", "box_blue", "cabinet")),
             _furnished(-1.0, 0.2, z0=upper, yaw_deg=180, only=("table_top", "table_legs", "box_red", "box_blue",
                                                                 "sofa"))]
    bound = np.array([[-hx, -hy, 0.0], [hx, hy, 2 * STOREY_H + SLAB_T]])
    return _assemble(_merge(parts, *rooms), bound, seed)


def two_storey_path() -> list[tuple[float, float, float]]:
    """Round the ground floor, up the stair, round the upper floor."""
    x0, x1, y0, y1 = STAIR
    mid, upper = (y0 + y1) / 2, STOREY_H + SLAB_T
    return [(-2.2, -0.5, 0), (-2.2, 1.4, 0), (2.2, 1.4, 0), (2.2, -0.4, 0), (-1.8, -0.4, 0), (-1.8, mid, 0),
            (x0 - 0.3, mid, 0), (x1 + 0.2, mid, upper), (2.6, 1.4, upper), (-2.2, 1.4, upper), (-2.2, -0.2, upper)]


def _resampled(points: np.ndarray, step: float) -> np.ndarray:
    """Points every `step` metres along a polyline."""
    lengths = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(lengths)])
    at = np.arange(0.0, s[-1], step)
    return np.stack([np.interp(at, s, points[:, i]) for i in range(points.shape[1])], 1)


def _smoothed(values: np.ndarray, window: int) -> np.ndarray:
    """A moving average along the first axis (ends held)."""
    if window <= 1:
        return values
    padded = np.concatenate([np.repeat(values[:1], window, 0), values, np.repeat(values[-1:], window, 0)])
    kernel = np.ones(window) / window
    out = np.stack([np.convolve(padded[:, i], kernel, mode="same") for i in range(values.shape[1])], 1)
    return out[window:-window]


def walk(waypoints: list[tuple[float, float, float]], step_m: float = 0.025, seed: int = 0) -> np.ndarray:
    """(N, 4, 4) poses of a camera carried along the waypoints (x, y, floor height) at eye height: corners rounded
    over half a metre (the view turns over two), looking ahead along the walk and panning +-25 degrees to
    either side every 5 m (at most 3 degrees a frame), a few centimetres of sway."""
    rng = np.random.default_rng([seed, 0x1A6])
    phase = rng.uniform(0.0, 2.0 * np.pi, 3)
    ground = _smoothed(_resampled(np.asarray(waypoints, dtype=np.float64), step_m), int(0.5 / step_m))
    heading = np.gradient(ground[:, :2], axis=0)
    heading = _smoothed(heading / np.maximum(np.linalg.norm(heading, axis=1, keepdims=True), 1e-9),
                        int(2.0 / step_m))
    s = np.arange(len(ground)) * step_m
    pan = np.radians(25.0) * np.sin(2 * np.pi * s / 5.0 + phase[0])
    c, sn = np.cos(pan), np.sin(pan)
    look = np.stack([c * heading[:, 0] - sn * heading[:, 1], sn * heading[:, 0] + c * heading[:, 1]], 1)
    look /= np.maximum(np.linalg.norm(look, axis=1, keepdims=True), 1e-9)
    eye = ground + [0.0, 0.0, EYE_H]
    eye[:, 2] += 0.04 * np.sin(2 * np.pi * s / 1.3 + phase[1])
    target = eye + np.concatenate([2.0 * look, np.full((len(eye), 1), -0.5)], 1)
    target[:, 2] += 0.3 * np.sin(2 * np.pi * s / 3.7 + phase[2])
    return np.stack([look_at(eye[i], target[i]) for i in range(len(eye))])


LAYOUTS: dict[str, tuple[Callable[[int], SyntheticScene], Callable[[], list]]] = {
    "flat": (build_flat, flat_path),
    "corridor_loop": (build_corridor_loop, corridor_loop_path),
    "two_storey": (build_two_storey, two_storey_path),
}


def generate_large_scene(out_dir, name: str, width: int = 320, height: int = 240, seed: int = 0,
                         step_m: float = 0.025, max_frames: Optional[int] = None,
                         sensor: Optional[SensorModel] = None) -> Path:
    """Render the walk through scene `name` (one of SCENES) into the TUM folder `out_dir` (new or empty)."""
    if name not in LAYOUTS:
        raise SyntheticSceneError(f"unknown large scene {name!r}: use one of {SCENES}")
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise SyntheticSceneError(f"{out} already exists and is not an empty folder: delete it or pick a new one")
    build, path = LAYOUTS[name]
    poses = walk(path(), step_m, seed)[:max_frames]
    written = write_tum_sequence(out, build(seed), poses, default_intrinsics(width, height),
                                 SensorModel() if sensor is None else sensor, seed)
    settings = json.loads((written / "scene.json").read_text())
    settings["large_scene"] = {"name": name, "step_m": step_m, "path_m": float(step_m * (len(poses) - 1))}
    (written / "scene.json").write_text(json.dumps(settings, indent=2) + "\n")
    return written
