"""The embedded synthetic RGB-D scene: a furnished room, a hand-held camera path and a Kinect-like sensor.

This is the default input of `eslam demo` and the data of the test suite, so it has to exercise a real dense SLAM
system: textured surfaces for the photometric losses, furniture for geometry, and the defects of a real depth
sensor (noise growing with distance, holes at depth edges, on shiny parts and at grazing angles).

World frame: metres, z up; the room spans `scene.bound` = [[-2, -1.5, 0], [2, 1.5, 2.6]]. Cameras use OpenCV axes
(x right, y down, z forward) and poses are camera-to-world, like everywhere in eslam_core.

Pipeline:  build_room -> handheld_trajectory -> render_frame (per pose) -> write_tum_sequence.
`generate_scene` runs all of it; `ensure_scene` caches the result so a demo generates it once.
Everything is deterministic given the seed.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Optional

import numpy as np
import trimesh
from PIL import Image
from scipy import ndimage

from eslam_core.camera import Intrinsics
from eslam_core.geometry import matrix_to_quaternion_xyzw, quaternion_xyzw_to_matrix, rotvec_to_matrix
from eslam_core.rendering.raycast import camera_rays, cast_rays

FPS = 30.0  # frame rate of written sequences: timestamps are index / FPS
DEPTH_SCALE = 5000.0  # TUM convention: stored uint16 = metres * DEPTH_SCALE
FORMAT_VERSION = 1  # bump when the generator's output changes, so cached scenes are regenerated
ROOM_SIZE = (4.0, 3.0, 2.6)  # x, y, z extent of the room in metres
MAX_EDGE_M = 0.3  # big flat faces are split until no edge is longer than this
HORIZONTAL_FOV_DEG = 61.0  # of the default camera (about a Kinect's)


class SyntheticSceneError(ValueError):
    """Bad argument to the synthetic-scene generator; the message says what to change."""


# ----------------------------------------------------------------------------------------------------------------
# Procedural textures
# ----------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ValueNoise:
    """Smooth 3D value noise: random values on an integer lattice, interpolated with a smoothstep.

    The lattice is hashed through a permutation table, so the noise is defined everywhere (period 256 cells)
    and fully determined by the seed.
    """

    permutation: np.ndarray  # (512,) int64: a permutation of 0..255, repeated twice to avoid wrapping indices
    lattice_values: np.ndarray  # (256,) float64 in [0, 1]

    @classmethod
    def from_seed(cls, seed: int) -> "ValueNoise":
        rng = np.random.default_rng([seed, 0x7E47])
        perm = rng.permutation(256).astype(np.int64)
        return cls(np.concatenate([perm, perm]), rng.random(256))

    def noise(self, points: np.ndarray, frequency: float) -> np.ndarray:
        """Noise in [0, 1] at (N, 3) points, with `frequency` lattice cells per metre."""
        scaled = points * frequency
        cell = np.floor(scaled)
        frac = scaled - cell
        sx, sy, sz = (frac * frac * (3.0 - 2.0 * frac)).T  # zero slope at cell faces: no visible lattice seams
        x0, y0, z0 = (cell.astype(np.int64) & 255).T
        x1, y1, z1 = (x0 + 1) & 255, (y0 + 1) & 255, (z0 + 1) & 255
        p, values = self.permutation, self.lattice_values

        def lerp(a: np.ndarray, b: np.ndarray, s: np.ndarray) -> np.ndarray:
            return a + s * (b - a)

        def along_z(hxy: np.ndarray) -> np.ndarray:  # hxy: hash of the (x, y) column of lattice points
            return lerp(values[p[hxy + z0]], values[p[hxy + z1]], sz)

        hx0, hx1 = p[x0], p[x1]
        near_x = lerp(along_z(p[hx0 + y0]), along_z(p[hx0 + y1]), sy)
        far_x = lerp(along_z(p[hx1 + y0]), along_z(p[hx1 + y1]), sy)
        return lerp(near_x, far_x, sx)

    def fractal(self, points: np.ndarray, frequency: float, octaves: int = 3) -> np.ndarray:
        """Sum of octaves (each twice the frequency, half the amplitude), normalised to [0, 1]."""
        total = np.zeros(len(points))
        norm = 0.0
        for octave in range(octaves):
            amplitude = 0.5**octave
            total += amplitude * self.noise(points, frequency * 2.0**octave)
            norm += amplitude
        return total / norm


@dataclass(frozen=True)
class Texture:
    """Appearance of one part: a pattern blending `base` towards `accent`, times a fine multiplicative grain.

    Patterns (`pattern`):
      - "stripes": wavy stripes across `direction` (wallpaper);
      - "checker": soft-edged tiles on the plane whose normal is `direction` (floor tiles);
      - "wood":    growth rings around an axis along `direction` through `origin`, grain stretched along it;
      - "mottled": contrast-stretched fractal noise (plaster, fabric, painted metal);
      - "tiles":   thin seams of `accent` on a square grid, `frequency` lines per metre, in the plane whose normal
                   is `direction` (a suspended ceiling, panelled walls).
    Frequencies are in cycles per metre; keep them below ~25 so that the pattern does not alias at 320x240.
    """

    pattern: str
    base: tuple[float, float, float]
    accent: tuple[float, float, float]
    frequency: float
    direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    grain: float = 0.15  # relative amplitude of the fine grain (0 = none)
    grain_frequency: float = 24.0
    noise_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)  # decorrelates the noise of different parts

    def __post_init__(self) -> None:
        if self.pattern not in _PATTERNS:
            raise SyntheticSceneError(f"unknown texture pattern {self.pattern!r}: use one of {sorted(_PATTERNS)}")


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _stripes(tex: Texture, p: np.ndarray, noise: ValueNoise) -> np.ndarray:
    across = p @ _unit(tex.direction)
    wobble = 0.6 * (noise.fractal(p, 2.0) - 0.5)  # stripes meander by ~0.3 period: no two rows look the same
    wave = np.sin(2.0 * np.pi * (tex.frequency * across + wobble))
    return 0.5 + 0.5 * np.tanh(3.0 * wave) / np.tanh(3.0)


def _checker(tex: Texture, p: np.ndarray, noise: ValueNoise) -> np.ndarray:
    normal = _unit(tex.direction)
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    axis_u = _unit(np.cross(normal, helper))
    axis_v = np.cross(normal, axis_u)
    s = np.sin(np.pi * tex.frequency * (p @ axis_u)) * np.sin(np.pi * tex.frequency * (p @ axis_v))
    # tanh of the product gives the parity of the tile with a ~1 cm soft edge instead of an aliasing step
    return 0.5 + 0.5 * np.tanh(8.0 * s) / np.tanh(8.0)


def _wood(tex: Texture, p: np.ndarray, noise: ValueNoise) -> np.ndarray:
    axis = _unit(tex.direction)
    rel = p - np.asarray(tex.origin)
    along = rel @ axis
    radius = np.linalg.norm(rel - along[:, None] * axis, axis=1)
    stretched = rel - 0.85 * along[:, None] * axis  # noise varies slowly along the grain
    rings = tex.frequency * radius + 1.5 * noise.fractal(stretched, 4.0)
    return (rings - np.floor(rings)) ** 2  # sharp dark ring edge, slow ramp: the look of late/early wood


def _mottled(tex: Texture, p: np.ndarray, noise: ValueNoise) -> np.ndarray:
    return np.clip(0.5 + 2.2 * (noise.fractal(p, tex.frequency) - 0.5), 0.0, 1.0)


SEAM_WIDTH_M = 0.012  # of the "tiles" pattern's lines


def _tiles(tex: Texture, p: np.ndarray, noise: ValueNoise) -> np.ndarray:
    normal = _unit(tex.direction)
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    axis_u = _unit(np.cross(normal, helper))
    axis_v = np.cross(normal, axis_u)
    seams = []
    for axis in (axis_u, axis_v):
        cycles = tex.frequency * (p @ axis)
        distance = np.abs(cycles - np.round(cycles)) / tex.frequency  # metres to the nearest seam
        seams.append(np.exp(-((distance / SEAM_WIDTH_M) ** 2)))
    return np.maximum(*seams)


_PATTERNS = {"stripes": _stripes, "checker": _checker, "wood": _wood, "mottled": _mottled, "tiles": _tiles}


def texture_albedo(tex: Texture, points: np.ndarray, noise: ValueNoise) -> np.ndarray:
    """(N, 3) albedo in [0, 1] of a texture at (N, 3) world points."""
    p = points + np.asarray(tex.noise_offset)
    mix = _PATTERNS[tex.pattern](tex, p, noise)[:, None]
    colour = (1.0 - mix) * np.asarray(tex.base) + mix * np.asarray(tex.accent)
    grain = 1.0 + tex.grain * (2.0 * noise.fractal(p + 101.0, tex.grain_frequency, octaves=2) - 1.0)
    return np.clip(colour * grain[:, None], 0.0, 1.0)


# ----------------------------------------------------------------------------------------------------------------
# Room geometry
# ----------------------------------------------------------------------------------------------------------------

# Part names in part-id order; `SyntheticScene.part_ids` indexes this tuple.
PART_NAMES = (
    "floor", "ceiling", "wall_west", "wall_east", "wall_south", "wall_north",
    "table_top", "table_legs", "box_red", "box_blue", "cabinet", "sofa", "lamp", "painting", "lights",
)  # fmt: skip
WALL_PARTS = ("wall_west", "wall_east", "wall_south", "wall_north")

_TEXTURES = {
    "floor": Texture("checker", (0.55, 0.42, 0.30), (0.86, 0.82, 0.74), 1.0 / 0.3, (0, 0, 1), grain=0.25),
    "ceiling": Texture("mottled", (0.90, 0.89, 0.86), (0.62, 0.64, 0.70), 3.0, grain=0.12),
    "wall_west": Texture("stripes", (0.86, 0.80, 0.64), (0.30, 0.42, 0.60), 6.0, (0, 1, 0)),
    "wall_east": Texture("stripes", (0.88, 0.82, 0.74), (0.55, 0.30, 0.26), 4.0, (0, 0, 1)),
    "wall_south": Texture("stripes", (0.72, 0.80, 0.70), (0.30, 0.48, 0.38), 5.0, (1, 0, 1)),
    "wall_north": Texture("mottled", (0.88, 0.82, 0.70), (0.42, 0.38, 0.36), 6.0, grain=0.2),
    "table_top": Texture("wood", (0.62, 0.40, 0.22), (0.32, 0.18, 0.08), 25.0, (1, 0, 0), (0.0, 0.2, 0.3)),
    "table_legs": Texture("mottled", (0.30, 0.18, 0.10), (0.45, 0.30, 0.18), 12.0),
    "box_red": Texture("stripes", (0.80, 0.15, 0.12), (0.95, 0.85, 0.30), 10.0, (1, 1, 0)),
    "box_blue": Texture("mottled", (0.15, 0.25, 0.70), (0.85, 0.88, 0.95), 10.0),
    "cabinet": Texture("stripes", (0.30, 0.45, 0.58), (0.82, 0.86, 0.90), 7.0, (0, 0, 1)),
    "sofa": Texture("mottled", (0.58, 0.22, 0.22), (0.82, 0.52, 0.40), 14.0, grain=0.3),
    "lamp": Texture("mottled", (0.06, 0.06, 0.07), (0.20, 0.20, 0.22), 8.0),  # dark metal: the sensor fails on it
    "painting": Texture("mottled", (0.92, 0.72, 0.20), (0.10, 0.28, 0.62), 5.0, grain=0.1),
    "lights": Texture("mottled", (0.99, 0.99, 0.96), (0.96, 0.96, 0.93), 2.0, grain=0.01),  # flush light panels
}


def _grid_box(extents, center=(0.0, 0.0, 0.0), max_edge: float = MAX_EDGE_M, inward: bool = False) -> trimesh.Trimesh:
    """Closed box whose faces are regular grids with edges no longer than `max_edge`.

    `inward=True` flips the winding so that normals point inside (the room shell, seen from within).
    """
    extents = np.asarray(extents, dtype=np.float64)
    half = extents / 2.0
    steps = np.maximum(1, np.ceil(extents / max_edge).astype(int))
    vertices, faces = [], []
    for normal_axis in range(3):
        # (axis_a, axis_b, normal_axis) is cyclic, so e_a x e_b = +e_normal
        axis_a, axis_b = (normal_axis + 1) % 3, (normal_axis + 2) % 3
        a = np.linspace(-half[axis_a], half[axis_a], steps[axis_a] + 1)
        b = np.linspace(-half[axis_b], half[axis_b], steps[axis_b] + 1)
        grid_a, grid_b = np.meshgrid(a, b, indexing="ij")
        na, nb = len(a), len(b)
        idx = np.arange(na * nb).reshape(na, nb)
        v00, v10, v11, v01 = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
        quads = np.stack([v00, v10, v11, v01], -1).reshape(-1, 4)
        for sign in (1.0, -1.0):
            side = np.zeros((na * nb, 3))
            side[:, axis_a] = grid_a.ravel()
            side[:, axis_b] = grid_b.ravel()
            side[:, normal_axis] = sign * half[normal_axis]
            tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
            if sign < 0:
                tris = tris[:, ::-1]
            faces.append(tris + sum(len(v) for v in vertices))
            vertices.append(side)
    mesh = trimesh.Trimesh(np.concatenate(vertices) + np.asarray(center), np.concatenate(faces), process=True)
    if inward:
        mesh.invert()
    return mesh


def _cylinder(radius: float, height: float, base_center) -> trimesh.Trimesh:
    mesh = trimesh.creation.cylinder(radius=radius, height=height, sections=24)
    mesh.apply_translation(np.asarray(base_center, dtype=np.float64) + [0.0, 0.0, height / 2.0])
    return mesh


def _on_floor(extents, x: float, y: float, z0: float = 0.0, yaw_deg: float = 0.0) -> trimesh.Trimesh:
    """Box standing on the plane z = z0, centred at (x, y), turned by `yaw_deg` about z."""
    box = _grid_box(extents)
    box.apply_transform(trimesh.transformations.rotation_matrix(math.radians(yaw_deg), [0, 0, 1]))
    box.apply_translation([x, y, z0 + extents[2] / 2.0])
    return box


def _room_parts() -> dict[str, list[trimesh.Trimesh]]:
    """The furniture layout (fixed; the seed only changes textures). Every object is below 1.1 m, so a camera
    at 1.2-1.7 m height anywhere >= 0.5 m from the walls is in free space."""
    gap = 0.01  # furniture stands 1 cm off the walls: no coplanar faces fighting for the same pixels
    half_x, half_y = ROOM_SIZE[0] / 2.0, ROOM_SIZE[1] / 2.0
    table_x, table_y, table_h, top_size = 0.1, 0.0, 0.75, (1.2, 0.8, 0.04)
    legs = [
        _on_floor((0.05, 0.05, table_h - top_size[2]), table_x + sx * 0.54, table_y + sy * 0.34)
        for sx in (-1, 1)
        for sy in (-1, 1)
    ]
    sofa_y = half_y - gap - 0.85 / 2.0
    sofa = [
        _on_floor((1.8, 0.85, 0.40), 0.2, sofa_y),  # seat
        _on_floor((1.8, 0.20, 0.45), 0.2, half_y - gap - 0.10, z0=0.40),  # back
        _on_floor((0.20, 0.65, 0.20), 0.2 - 0.8, sofa_y - 0.10, z0=0.40),  # arms, in front of the back
        _on_floor((0.20, 0.65, 0.20), 0.2 + 0.8, sofa_y - 0.10, z0=0.40),
    ]
    lamp_x, lamp_y = half_x - 0.35, -half_y + 0.35
    lamp = [
        _cylinder(0.16, 0.03, (lamp_x, lamp_y, 0.0)),
        _on_floor((0.035, 0.035, 0.75), lamp_x, lamp_y, z0=0.03),  # square pole: a grid box, so no long slivers
        trimesh.creation.icosphere(subdivisions=2, radius=0.14).apply_translation([lamp_x, lamp_y, 0.90]),
    ]
    return {
        "room": [_grid_box(ROOM_SIZE, (0.0, 0.0, ROOM_SIZE[2] / 2.0), inward=True)],
        "table_top": [_on_floor(top_size, table_x, table_y, z0=table_h - top_size[2])],
        "table_legs": legs,
        # the boxes stay >= 0.25 m inside the table edges, so the walking camera never comes close to them
        "box_red": [_on_floor((0.28, 0.20, 0.14), table_x - 0.30, table_y - 0.05, z0=table_h)],
        "box_blue": [_on_floor((0.16, 0.16, 0.26), table_x + 0.25, table_y + 0.10, z0=table_h, yaw_deg=30.0)],
        "cabinet": [_on_floor((0.45, 1.0, 0.9), -half_x + gap + 0.225, 0.55)],
        "sofa": sofa,
        "lamp": lamp,
        "painting": [_grid_box((0.9, 0.03, 0.6), (0.2, -half_y + 0.002 + 0.015, 1.5))],
    }


def _room_shell_parts(shell: trimesh.Trimesh) -> np.ndarray:
    """Part id of each face of the room shell, from the direction its (inward) normal points."""
    normals = shell.face_normals
    by_normal = {
        "floor": (0, 0, 1), "ceiling": (0, 0, -1),
        "wall_west": (1, 0, 0), "wall_east": (-1, 0, 0), "wall_south": (0, 1, 0), "wall_north": (0, -1, 0),
    }  # fmt: skip
    ids = np.full(len(normals), -1, dtype=np.int64)
    for name, direction in by_normal.items():
        ids[normals @ np.asarray(direction, dtype=np.float64) > 0.99] = PART_NAMES.index(name)
    assert (ids >= 0).all(), "room shell faces must be axis-aligned"
    return ids


@dataclass(eq=False)
class SyntheticScene:
    """The ground-truth room: one mesh, the part each face belongs to, and the textures of the parts."""

    mesh: trimesh.Trimesh  # also carries the part ids as mesh.face_attributes["part"]
    part_ids: np.ndarray  # (F,) int64 index into PART_NAMES, one per face
    bound: np.ndarray  # (2, 3) min and max corner of the room, metres
    textures: dict[str, Texture]  # by part name
    noise: ValueNoise
    seed: int

    def part_mask(self, face_ids: np.ndarray, *names: str) -> np.ndarray:
        """True where a face index (-1 = no hit) belongs to one of the named parts."""
        unknown = set(names) - set(PART_NAMES)
        if unknown:
            raise SyntheticSceneError(f"unknown part names {sorted(unknown)}: use names from PART_NAMES")
        face_ids = np.asarray(face_ids)
        wanted = np.isin(self.part_ids, [PART_NAMES.index(n) for n in names])
        return (face_ids >= 0) & wanted[np.clip(face_ids, 0, None)]

    def albedo(self, points: np.ndarray, face_ids: np.ndarray) -> np.ndarray:
        """(N, 3) albedo in [0, 1] at (N, 3) surface points lying on the given (N,) faces."""
        points = np.asarray(points, dtype=np.float64)
        face_ids = np.asarray(face_ids)
        if points.ndim != 2 or points.shape[1] != 3 or face_ids.shape != (len(points),):
            raise SyntheticSceneError(
                f"albedo needs (N, 3) points and (N,) face ids, got {points.shape} and {face_ids.shape}"
            )
        if len(face_ids) and (face_ids.min() < 0 or face_ids.max() >= len(self.part_ids)):
            raise SyntheticSceneError(
                f"face ids must be in [0, {len(self.part_ids)}); drop rays that hit nothing (face -1) first"
            )
        parts = self.part_ids[face_ids]
        out = np.zeros((len(points), 3))
        for part in np.unique(parts):
            sel = parts == part
            out[sel] = texture_albedo(self.textures[PART_NAMES[part]], points[sel], self.noise)
        return out

    def vertex_colors(self) -> np.ndarray:
        """(V, 4) uint8 RGBA albedo at the mesh vertices, for writing the ground truth as a coloured PLY."""
        # Parts never share vertices (each was built separately), so any face through a vertex gives its part.
        vertex_face = np.zeros(len(self.mesh.vertices), dtype=np.int64)
        vertex_face[self.mesh.faces.ravel()] = np.repeat(np.arange(len(self.mesh.faces)), 3)
        rgb = self.albedo(self.mesh.vertices, vertex_face)
        alpha = np.ones((len(rgb), 1))
        return np.round(np.concatenate([rgb, alpha], axis=1) * 255.0).astype(np.uint8)


def build_room(seed: int = 0) -> SyntheticScene:
    """The furnished room (about 4.0 x 3.0 x 2.6 m, z up) with seeded procedural textures.

    The geometry is the same for every seed; the seed changes the noise in the textures.
    """
    half = np.array(ROOM_SIZE[:2]) / 2.0
    bound = np.array([[-half[0], -half[1], 0.0], [half[0], half[1], ROOM_SIZE[2]]])
    return _assemble(_room_parts(), bound, seed)


def build_long_room(seed: int = 0) -> SyntheticScene:
    """A room twice as long as the furnished room (8.0 x 3.0 x 2.6 m, z up): its furniture in the west half, and
    the table, boxes, sofa and painting again in the east half. A camera that walks along it sees far beyond its
    first view (the map has to grow)."""
    length, width, height = 2 * ROOM_SIZE[0], ROOM_SIZE[1], ROOM_SIZE[2]
    parts: dict[str, list[trimesh.Trimesh]] = {"room": [_grid_box((length, width, height), (0.0, 0.0, height / 2.0),
                                                                  inward=True)]}
    east = ("table_top", "table_legs", "box_red", "box_blue", "sofa", "painting")
    for dx, names in ((-ROOM_SIZE[0] / 2, None), (ROOM_SIZE[0] / 2, east)):
        for name, pieces in _room_parts().items():
            if name != "room" and (names is None or name in names):
                parts.setdefault(name, []).extend(p.copy().apply_translation([dx, 0.0, 0.0]) for p in pieces)
    bound = np.array([[-length / 2.0, -width / 2.0, 0.0], [length / 2.0, width / 2.0, height]])
    return _assemble(parts, bound, seed)


def _assemble(parts: dict[str, list[trimesh.Trimesh]], bound: np.ndarray, seed: int,
              textures: Optional[dict[str, Texture]] = None) -> SyntheticScene:
    """One mesh of the parts; `textures` replaces the default look of the parts it names."""
    meshes, ids = [], []
    for name, pieces in parts.items():
        for piece in pieces:
            meshes.append(piece)
            if name == "room":
                ids.append(_room_shell_parts(piece))
            else:
                ids.append(np.full(len(piece.faces), PART_NAMES.index(name), dtype=np.int64))
    # concatenate without merging: parts keep their own vertices (so vertex colours are unambiguous)
    vertices = np.concatenate([m.vertices for m in meshes])
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    faces = np.concatenate([m.faces + off for m, off in zip(meshes, offsets)])
    part_ids = np.concatenate(ids)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.face_attributes["part"] = part_ids
    rng = np.random.default_rng([seed, 0x5EED])
    looks = {**_TEXTURES, **(textures or {})}
    textures = {name: replace(tex, noise_offset=tuple(rng.uniform(-50.0, 50.0, 3))) for name, tex in looks.items()}
    return SyntheticScene(mesh, part_ids, bound, textures, ValueNoise.from_seed(seed), seed)


# ----------------------------------------------------------------------------------------------------------------
# Hand-held camera path
# ----------------------------------------------------------------------------------------------------------------


def look_at(eye, target, roll_rad: float = 0.0, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) at `eye` looking at `target`, image 'up' towards world `up`,
    then turned by `roll_rad` about the viewing axis."""
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    if np.linalg.norm(forward) < 1e-9:
        raise SyntheticSceneError("look_at: eye and target coincide; give a target away from the camera")
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(right) < 1e-6:
        raise SyntheticSceneError("look_at: viewing direction is parallel to 'up'; tilt the target or change up")
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)  # completes a right-handed (x right, y down, z forward) frame
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, down, forward], axis=1) @ rotvec_to_matrix([0.0, 0.0, roll_rad])
    pose[:3, 3] = eye
    return pose


def _sinusoids(t: np.ndarray, amplitudes, frequencies_hz, phases) -> np.ndarray:
    """sum_k a_k sin(2 pi f_k t + phi_k), evaluated at every t."""
    args = 2.0 * np.pi * np.outer(t, frequencies_hz) + np.asarray(phases)
    return np.sin(args) @ np.asarray(amplitudes)


def handheld_trajectory(n_frames: int, fps: float = 30.0, seed: int = 0, speed: float = 0.25) -> np.ndarray:
    """(n_frames, 4, 4) camera-to-world poses of a person walking slowly round the table holding a camera.

    Positions follow a wobbly loop (|x| <= 1.35 m, |y| <= 0.9 m: >= 0.5 m from every wall; height 1.2-1.7 m),
    travelled at `speed` m/s +-20 %. The camera looks across the table at a slowly drifting target, with a few
    degrees of roll and a sub-millimetre / ~0.1 degree hand shake. The same seed gives the same path.
    """
    if n_frames < 1:
        raise SyntheticSceneError(f"n_frames must be >= 1, got {n_frames}")
    if fps <= 0:
        raise SyntheticSceneError(f"fps must be positive, got {fps}")
    if not 0.0 < speed <= 2.0:
        raise SyntheticSceneError(f"speed must be in (0, 2] m/s (a walking person), got {speed}")
    rng = np.random.default_rng([seed, 0x7A1])
    t = np.arange(n_frames) / fps

    # Path of the loop as a function of its angle phi: an ellipse with two harmonics, bobbing up and down.
    start = rng.uniform(0.0, 2.0 * np.pi)
    turn = rng.choice([-1.0, 1.0])  # walk clockwise or anticlockwise
    harm = rng.uniform(0.0, 2.0 * np.pi, 5)

    def loop(phi: np.ndarray) -> np.ndarray:
        x = 1.2 * np.cos(phi) + 0.08 * np.cos(2.0 * phi + harm[0]) + 0.07 * np.sin(3.0 * phi + harm[1])
        y = 0.75 * np.sin(phi) + 0.08 * np.sin(2.0 * phi + harm[2]) + 0.07 * np.cos(3.0 * phi + harm[3])
        z = 1.45 + 0.17 * np.sin(2.0 * phi + harm[4]) + 0.05 * np.sin(5.0 * phi)
        return np.stack([x, y, z], axis=1)

    # Walking speed varies by +-20 % around `speed`; distance walked -> loop angle through the arc-length table.
    modulation_hz = rng.uniform(0.15, 0.3)
    walked = speed * (t + 0.2 / (2.0 * np.pi * modulation_hz) * (1.0 - np.cos(2.0 * np.pi * modulation_hz * t)))
    laps = int(walked[-1] / 5.0) + 2  # one lap is > 5 m long
    phi_table = start + turn * np.linspace(0.0, 2.0 * np.pi * laps, 4000 * laps)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(loop(phi_table), axis=0), axis=1))])
    positions = loop(np.interp(walked, arc, phi_table))

    # The operator looks across the table at the far side of the room (target pushed 0.7 m beyond the table, away
    # from the camera), so each view holds furniture in front of walls at 1-4 m; the target drifts slowly so the
    # view direction is not locked to the path.
    target = np.array([0.1, 0.0, 0.8]) + np.stack(
        [
            _sinusoids(t, [0.30], [rng.uniform(0.04, 0.08)], rng.uniform(0, 2 * np.pi, 1)),
            _sinusoids(t, [0.20], [rng.uniform(0.04, 0.08)], rng.uniform(0, 2 * np.pi, 1)),
            _sinusoids(t, [0.12], [rng.uniform(0.03, 0.06)], rng.uniform(0, 2 * np.pi, 1)),
        ],
        axis=1,
    )
    away = target[:, :2] - positions[:, :2]
    target[:, :2] += 0.7 * away / np.linalg.norm(away, axis=1, keepdims=True)
    roll = np.radians(_sinusoids(t, [2.5, 1.0], [rng.uniform(0.1, 0.2), rng.uniform(0.3, 0.5)], rng.uniform(0, 7, 2)))

    # Hand shake: a few 2-7 Hz tremors, ~0.3 mm and ~0.1 degree in total.
    def shake(amplitude: float) -> np.ndarray:
        return np.stack(
            [_sinusoids(t, rng.uniform(0.3, 0.6, 3) * amplitude / 1.5, rng.uniform(2, 7, 3), rng.uniform(0, 7, 3))
             for _ in range(3)],
            axis=1,
        )  # fmt: skip

    shake_translation = shake(0.0003)
    shake_rotation = shake(np.radians(0.1))

    poses = np.empty((n_frames, 4, 4))
    for i in range(n_frames):
        pose = look_at(positions[i] + shake_translation[i], target[i], roll[i])
        pose[:3, :3] = pose[:3, :3] @ rotvec_to_matrix(shake_rotation[i])
        poses[i] = pose
    return poses


def walkthrough_trajectory(n_frames: int, step_m: float = 0.025, seed: int = 0) -> np.ndarray:
    """(n_frames, 4, 4) poses of a camera carried along the long room (`build_long_room`) from x = -3 m, `step_m`
    per frame (0.75 m/s at 30 Hz), 0.65 m from the north wall's side of the centre, looking across the room at the
    furniture and the south wall, swaying by a few centimetres and degrees."""
    if n_frames < 1 or not 0.0 < step_m <= 0.1:
        raise SyntheticSceneError(f"walkthrough_trajectory needs n_frames >= 1 and 0 < step_m <= 0.1 m, got "
                                  f"{n_frames} and {step_m}")
    rng = np.random.default_rng([seed, 0xD00])
    k = np.arange(n_frames)
    phase = rng.uniform(0.0, 2.0 * np.pi, 3)
    x = np.minimum(-3.0 + step_m * k, 3.0)
    y = 0.65 + 0.06 * np.sin(2.0 * np.pi * k / 90.0 + phase[0])
    z = 1.5 + 0.05 * np.sin(2.0 * np.pi * k / 70.0 + phase[1])
    target_x = x + 0.4 * np.sin(2.0 * np.pi * k / 120.0 + phase[2])
    return np.stack([look_at([x[i], y[i], z[i]], [target_x[i], -0.9, 0.4]) for i in range(n_frames)])


# ----------------------------------------------------------------------------------------------------------------
# Rendering with a depth-sensor model
# ----------------------------------------------------------------------------------------------------------------

# Directional lights (towards the light, intensity) and ambient term of the Lambert shading.
LIGHTS = (((0.3, 0.2, 1.0), 0.5), ((-0.6, -0.7, 0.4), 0.3), ((0.7, 0.5, 0.3), 0.2))
AMBIENT = 0.45


@dataclass(frozen=True)
class SensorModel:
    """Defects of a Kinect-like RGB-D sensor. None (or 0) switches an effect off; `ideal()` switches all off."""

    noise_base_m: float = 0.0012  # depth noise sigma(z) = base + quadratic * (z - z0)^2 (Kinect-like)
    noise_quadratic: float = 0.0019
    noise_z0_m: float = 0.4
    edge_jump_m: Optional[float] = 0.06  # drop pixels where the 3x3 depth range exceeds the surface slope + this
    edge_dilation_px: int = 1  # ... then grow those holes by this many pixels
    shiny_parts: tuple[str, ...] = ("lamp",)  # dark / specular parts where the sensor mostly fails
    shiny_dropout: float = 0.85  # fraction of their pixels without depth
    max_incidence_deg: Optional[float] = 80.0  # drop depth where the ray meets the surface more obliquely
    min_range_m: Optional[float] = 0.3  # no depth closer than this ...
    max_range_m: Optional[float] = 5.0  # ... or farther than this (planar z)
    random_dropout: float = 0.005  # fraction of pixels lost at random
    depth_quantum_m: Optional[float] = 1.0 / DEPTH_SCALE  # depth rounded to multiples of this
    rgb_noise_std: float = 2.0  # Gaussian colour noise, in 8-bit grey levels

    def __post_init__(self) -> None:
        for name in ("shiny_dropout", "random_dropout"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise SyntheticSceneError(f"SensorModel.{name} is a fraction: give a value in [0, 1]")
        for name in ("noise_base_m", "noise_quadratic", "rgb_noise_std", "edge_dilation_px"):
            if getattr(self, name) < 0:
                raise SyntheticSceneError(f"SensorModel.{name} must be >= 0 (0 switches it off)")
        for name in ("edge_jump_m", "min_range_m", "max_range_m", "depth_quantum_m"):
            value = getattr(self, name)
            if value is not None and value <= 0:
                raise SyntheticSceneError(f"SensorModel.{name} must be positive, or None to switch it off")
        if self.max_incidence_deg is not None and not 0.0 < self.max_incidence_deg <= 90.0:
            raise SyntheticSceneError("SensorModel.max_incidence_deg must be in (0, 90], or None to switch it off")
        unknown = set(self.shiny_parts) - set(PART_NAMES)
        if unknown:
            raise SyntheticSceneError(f"SensorModel.shiny_parts: unknown parts {sorted(unknown)}; see PART_NAMES")

    @classmethod
    def ideal(cls) -> "SensorModel":
        """A perfect sensor: exact planar depth wherever a surface is hit, noise-free colour."""
        return cls(
            noise_base_m=0.0, noise_quadratic=0.0, edge_jump_m=None, edge_dilation_px=0, shiny_parts=(),
            shiny_dropout=0.0, max_incidence_deg=None, min_range_m=None, max_range_m=None, random_dropout=0.0,
            depth_quantum_m=None, rgb_noise_std=0.0,
        )  # fmt: skip

    def to_json(self) -> dict:
        return json.loads(json.dumps(asdict(self)))

    @classmethod
    def from_json(cls, data: dict) -> "SensorModel":
        """Inverse of to_json (e.g. the "sensor" entry of a scene.json)."""
        unknown = set(data) - set(cls.__dataclass_fields__)
        if unknown:
            raise SyntheticSceneError(
                f"unknown sensor settings {sorted(unknown)}: regenerate the scene with this version of eslam_core"
            )
        data = dict(data)
        data["shiny_parts"] = tuple(data.get("shiny_parts", ()))
        return cls(**data)


def depth_noise_sigma(z: np.ndarray, sensor: SensorModel) -> np.ndarray:
    """Standard deviation (metres) of the depth noise at planar depth z."""
    return sensor.noise_base_m + sensor.noise_quadratic * (z - sensor.noise_z0_m) ** 2


def lambert_shading(normals: np.ndarray, view_dirs: np.ndarray) -> np.ndarray:
    """(N,) brightness of surfaces with (N, 3) unit normals seen along (N, 3) unit view directions.

    Normals are first turned towards the viewer, so the shading does not depend on the mesh's winding.
    The lights are directional: the brightness of a point is the same from every view (photo-consistent).
    """
    facing = normals * -np.sign(np.einsum("ij,ij->i", normals, view_dirs))[:, None]
    brightness = np.full(len(normals), AMBIENT)
    for direction, intensity in LIGHTS:
        brightness += intensity * np.clip(facing @ _unit(direction), 0.0, None)
    return brightness


def depth_edge_mask(depth: np.ndarray, cos_incidence: np.ndarray, fx: float, jump_m: float) -> np.ndarray:
    """True at depth discontinuities: where the depth range of the 3x3 neighbourhood exceeds what the pixel's own
    surface slope explains by more than `jump_m` (so slanted floors far away are not mistaken for edges)."""
    cos_c = np.clip(cos_incidence, math.cos(math.radians(85.0)), 1.0)
    slope_step = depth / fx * np.sqrt(1.0 - cos_c**2) / cos_c  # depth change per pixel along the surface
    spread = ndimage.maximum_filter(depth, size=3, mode="nearest") - ndimage.minimum_filter(depth, 3, mode="nearest")
    return spread > jump_m + 3.0 * slope_step  # 3 pixels: the 3x3 diagonal is 2 sqrt(2) steps long


def sensor_depth(
    ideal_depth: np.ndarray,
    cos_incidence: np.ndarray,
    shiny: np.ndarray,
    fx: float,
    sensor: SensorModel,
    rng: np.random.Generator,
) -> np.ndarray:
    """What the sensor reports for an exact planar depth image (0 = no surface): noise, holes, quantisation."""
    hit = ideal_depth > 0
    depth = ideal_depth + rng.standard_normal(ideal_depth.shape) * depth_noise_sigma(ideal_depth, sensor)
    missing = ~hit | (rng.random(ideal_depth.shape) < sensor.random_dropout)
    missing |= shiny & (rng.random(ideal_depth.shape) < sensor.shiny_dropout)
    if sensor.edge_jump_m is not None:
        edges = depth_edge_mask(ideal_depth, cos_incidence, fx, sensor.edge_jump_m)
        if sensor.edge_dilation_px > 0:
            edges = ndimage.binary_dilation(edges, iterations=sensor.edge_dilation_px)
        missing |= edges
    if sensor.max_incidence_deg is not None:
        missing |= cos_incidence < math.cos(math.radians(sensor.max_incidence_deg))
    if sensor.min_range_m is not None:
        missing |= ideal_depth < sensor.min_range_m
    if sensor.max_range_m is not None:
        missing |= ideal_depth > sensor.max_range_m
    if sensor.depth_quantum_m is not None:
        depth = np.round(depth / sensor.depth_quantum_m) * sensor.depth_quantum_m
    return np.where(missing, 0.0, np.maximum(depth, 0.0)).astype(np.float32)


def _check_pose(pose: np.ndarray) -> np.ndarray:
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise SyntheticSceneError(f"pose must be a finite 4x4 camera-to-world matrix, got shape {pose.shape}")
    rot = pose[:3, :3]
    if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) or np.linalg.det(rot) < 0:
        raise SyntheticSceneError("pose rotation is not a proper rotation (orthonormal, det +1); re-orthonormalise it")
    return pose


def render_frame(
    scene: SyntheticScene,
    intr: Intrinsics,
    pose: np.ndarray,
    rng: np.random.Generator,
    sensor: SensorModel = SensorModel(),
) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast one RGB-D frame: (rgb uint8 H x W x 3, depth float32 H x W metres, 0 = missing).

    Colour = albedo x Lambert shading + Gaussian noise (black where nothing is hit); depth = planar z through
    the sensor model. All randomness comes from `rng`.
    """
    pose = _check_pose(pose)
    origins, dirs, z_of_unit_ray = camera_rays(intr, pose)
    hits = cast_rays(scene.mesh, origins, dirs)
    hit = hits.face >= 0
    faces = hits.face[hit]
    normals = scene.mesh.face_normals[faces]

    radiance = np.zeros((len(dirs), 3))
    radiance[hit] = scene.albedo(hits.location[hit], faces) * lambert_shading(normals, dirs[hit])[:, None]
    cos_incidence = np.ones(len(dirs))
    cos_incidence[hit] = np.abs(np.einsum("ij,ij->i", normals, dirs[hit]))
    shiny = np.zeros(len(dirs), dtype=bool)
    shiny[hit] = scene.part_mask(faces, *sensor.shiny_parts) if sensor.shiny_parts else False

    shape = (intr.height, intr.width)
    ideal_depth = np.where(hit, hits.distance * z_of_unit_ray, 0.0).reshape(shape)
    depth = sensor_depth(ideal_depth, cos_incidence.reshape(shape), shiny.reshape(shape), intr.fx, sensor, rng)
    grey_levels = radiance.reshape(shape + (3,)) * 255.0
    if sensor.rgb_noise_std > 0:
        grey_levels = grey_levels + rng.standard_normal(grey_levels.shape) * sensor.rgb_noise_std
        grey_levels[~hit.reshape(shape)] = 0.0
    rgb = np.clip(np.round(grey_levels), 0, 255).astype(np.uint8)
    return rgb, depth


# ----------------------------------------------------------------------------------------------------------------
# Writing a TUM RGB-D sequence
# ----------------------------------------------------------------------------------------------------------------


rotation_to_quaternion = matrix_to_quaternion_xyzw
quaternion_to_rotation = quaternion_xyzw_to_matrix


def frame_rng(seed: int, index: int) -> np.random.Generator:
    """Random generator of frame `index`'s sensor noise: each frame is reproducible on its own."""
    return np.random.default_rng([seed, index])


def default_intrinsics(width: int = 320, height: int = 240) -> Intrinsics:
    """Pinhole camera with a ~61 degree horizontal field of view (about a Kinect's), centred principal point."""
    f = 0.5 * width / math.tan(math.radians(HORIZONTAL_FOV_DEG / 2.0))
    return Intrinsics(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0)


def _timestamp(index: int) -> str:
    return f"{index / FPS:.6f}"


def write_tum_sequence(
    out_dir, scene: SyntheticScene, poses: np.ndarray, intr: Intrinsics, sensor: SensorModel, seed: int
) -> Path:
    """Render every pose and write a TUM RGB-D folder; returns its path.

    Layout: rgb/NNNNNN.png, depth/NNNNNN.png (uint16, metres * 5000, 0 = missing), rgb.txt, depth.txt,
    groundtruth.txt (timestamp tx ty tz qx qy qz qw, camera-to-world, OpenCV axes), camera.json, mesh.ply
    (ground truth with vertex colours) and scene.json (settings; written last, it marks the folder complete).
    Frame i has timestamp i / 30 s and sensor noise from frame_rng(seed, i).
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
        raise SyntheticSceneError(f"poses must be an (N, 4, 4) array with N >= 1, got shape {poses.shape}")
    out = Path(out_dir)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(exist_ok=True)
    max_depth = np.iinfo(np.uint16).max / DEPTH_SCALE

    names = []
    for i, pose in enumerate(poses):
        rgb, depth = render_frame(scene, intr, pose, frame_rng(seed, i), sensor)
        name = f"{i:06d}.png"
        Image.fromarray(rgb).save(out / "rgb" / name)  # uint8 H x W x 3 -> mode "RGB"
        # depth beyond what uint16 can hold is not a measurement: store it as missing rather than clipped
        stored = np.where(depth <= max_depth, np.round(depth.astype(np.float64) * DEPTH_SCALE), 0).astype(np.uint16)
        Image.fromarray(stored).save(out / "depth" / name)  # uint16 -> mode "I;16", a 16-bit PNG
        names.append(name)

    for kind, title in (("rgb", "color images"), ("depth", "depth maps")):
        lines = [f"# {title}", f"# synthetic room, seed {scene.seed}", "# timestamp filename"]
        lines += [f"{_timestamp(i)} {kind}/{name}" for i, name in enumerate(names)]
        (out / f"{kind}.txt").write_text("\n".join(lines) + "\n")
    lines = ["# ground truth trajectory", "# camera-to-world, OpenCV camera axes", "# timestamp tx ty tz qx qy qz qw"]
    for i, pose in enumerate(poses):
        values = np.concatenate([pose[:3, 3], rotation_to_quaternion(pose[:3, :3])])
        lines.append(_timestamp(i) + " " + " ".join(f"{v:.9f}" for v in values))
    (out / "groundtruth.txt").write_text("\n".join(lines) + "\n")

    camera = {"width": intr.width, "height": intr.height, "fx": intr.fx, "fy": intr.fy, "cx": intr.cx,
              "cy": intr.cy, "depth_scale": DEPTH_SCALE}  # fmt: skip
    (out / "camera.json").write_text(json.dumps(camera, indent=2) + "\n")
    coloured = trimesh.Trimesh(scene.mesh.vertices, scene.mesh.faces, vertex_colors=scene.vertex_colors(),
                               process=False)  # fmt: skip
    coloured.export(out / "mesh.ply")
    settings = {
        "format_version": FORMAT_VERSION,
        "generator": "eslam_core.datasets.synthetic",
        "room_seed": scene.seed,
        "seed": seed,
        "n_frames": len(poses),
        "fps": FPS,
        "bound": scene.bound.tolist(),
        "camera": camera,
        "sensor": sensor.to_json(),
    }
    (out / "scene.json").write_text(json.dumps(settings, indent=2) + "\n")
    return out


# ----------------------------------------------------------------------------------------------------------------
# One call: generate, or reuse a cached generation
# ----------------------------------------------------------------------------------------------------------------


def generate_scene(
    out_dir, n_frames: int = 60, width: int = 320, height: int = 240, seed: int = 0,
    sensor: Optional[SensorModel] = None, layout: str = "room",
) -> Path:  # fmt: skip
    """Build the room, walk the camera through it and write the TUM folder `out_dir` (must be new or empty).

    The seed drives the textures, the camera path and the sensor noise. `sensor` defaults to SensorModel().
    `layout`: "room" (a hand-held loop round the table) or "long_room" (a walk along a room twice as long, see
    build_long_room and walkthrough_trajectory).
    """
    if layout not in ("room", "long_room"):
        raise SyntheticSceneError(f"unknown layout {layout!r}: use 'room' or 'long_room'")
    sensor = SensorModel() if sensor is None else sensor
    if width < 8 or height < 8:
        raise SyntheticSceneError(f"image size {width}x{height} is too small: use at least 8x8 pixels")
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise SyntheticSceneError(f"{out} already exists and is not an empty folder: delete it or pick a new one")
    if layout == "room":
        scene, poses = build_room(seed), handheld_trajectory(n_frames, fps=FPS, seed=seed)
    else:
        scene, poses = build_long_room(seed), walkthrough_trajectory(n_frames, seed=seed)
    return write_tum_sequence(out, scene, poses, default_intrinsics(width, height), sensor, seed)


def _expected_settings(n_frames: int, width: int, height: int, seed: int, sensor: SensorModel) -> dict:
    """The parts of scene.json that must match for a cached folder to be reused."""
    intr = default_intrinsics(width, height)
    camera = {"width": width, "height": height, "fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy,
              "depth_scale": DEPTH_SCALE}  # fmt: skip
    settings = {"format_version": FORMAT_VERSION, "room_seed": seed, "seed": seed, "n_frames": n_frames,
                "camera": camera, "sensor": sensor.to_json()}  # fmt: skip
    return json.loads(json.dumps(settings))


def _is_complete(folder: Path, expected: dict) -> bool:
    try:
        stored = json.loads((folder / "scene.json").read_text())
    except (OSError, ValueError):
        return False
    return all(stored.get(key) == value for key, value in expected.items())


def _remove_abandoned_partials(cache_dir: Path, name: str) -> None:
    """Delete temp folders of generations whose process died (an interrupted `eslam demo`)."""
    for partial in cache_dir.glob(f".{name}.partial-*"):
        try:
            pid = int(partial.name.split(".partial-")[1].split("-")[0])
            os.kill(pid, 0)  # raises if no such process
        except (ValueError, IndexError, ProcessLookupError):
            shutil.rmtree(partial, ignore_errors=True)
        except PermissionError:
            pass  # a live process of another user owns it


def ensure_scene(
    cache_dir, n_frames: int = 60, width: int = 320, height: int = 240, seed: int = 0,
    sensor: Optional[SensorModel] = None,
) -> Path:  # fmt: skip
    """Path of a generated scene under `cache_dir`, generating it only if no complete matching one is there.

    Each setting gets its own sub-folder (room-seed{seed}-{w}x{h}-{n}f-{hash}). A generation is written to a
    temporary folder and renamed into place when finished, so an interrupted run never leaves a folder that
    looks complete.
    """
    sensor = SensorModel() if sensor is None else sensor
    expected = _expected_settings(n_frames, width, height, seed, sensor)
    digest = _short_hash(json.dumps(expected, sort_keys=True))
    cache = Path(cache_dir)
    cache.mkdir(parents=True, exist_ok=True)
    target = cache / f"room-seed{seed}-{width}x{height}-{n_frames}f-{digest}"
    if _is_complete(target, expected):
        return target

    _remove_abandoned_partials(cache, target.name)
    partial = Path(tempfile.mkdtemp(prefix=f".{target.name}.partial-{os.getpid()}-", dir=cache))
    try:
        generate_scene(partial, n_frames=n_frames, width=width, height=height, seed=seed, sensor=sensor)
        if _is_complete(target, expected):  # a concurrent run finished first
            return target
        if target.exists():  # an incomplete or outdated folder: move it aside (named like a partial, so that an
            # interruption right now leaves it to the cleanup above), then replace it
            stale = Path(tempfile.mkdtemp(prefix=f".{target.name}.partial-{os.getpid()}-", dir=cache))
            target.rename(stale / "old")
            shutil.rmtree(stale, ignore_errors=True)
        try:
            partial.rename(target)
        except OSError:
            if not _is_complete(target, expected):  # not a concurrent run that finished first
                raise
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    return target


def _short_hash(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()[:10]
