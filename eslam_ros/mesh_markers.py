"""Triangle meshes as visualization_msgs/MarkerArray messages, written fast enough to publish a live map.

Two forms:
- a whole mesh (`serialize_mesh_marker_array`, `mesh_to_marker_array`): a DELETEALL marker (so blocks left over
  from a larger previous mesh vanish), then TRIANGLE_LIST markers of at most `max_triangles_per_marker` triangles;
- map blocks (`serialize_block_markers`): one TRIANGLE_LIST marker per block of the map, its id derived from the
  block's integer coordinates (`block_marker_id`), so a message can carry only the blocks that changed (ADD with
  the same id replaces a block in RViz and Foxglove) and those that became empty (DELETE).
Markers have three corner points per triangle, per-corner colours, identity pose and unit scale, in the mesh's
frame (e.g. "map").

Filling Marker.points with 100k-triangle meshes through Python Point objects takes over a second, so the
`serialize_*` functions write the message's CDR bytes directly with numpy; rclpy publishers accept them as-is
(`publisher.publish(data)`). `mesh_to_marker_array` builds the equivalent message object, for small meshes and for
checking.

Over `triangle_budget` triangles a whole mesh is subsampled: an evenly spaced subset of the faces is kept. Meshes
from marching cubes list their faces in spatial order, so this thins the surface uniformly (it shows holes up
close, which is acceptable for a live preview; save the full mesh to a file for close inspection).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any, Iterable, Mapping, Optional

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, Vector3
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from eslam_ros.cdr import CdrWriter
from eslam_ros.conversions import Stamp, to_time

# Colour of a mesh given without vertex colours: light grey, opaque.
DEFAULT_MESH_COLOR = (0.8, 0.8, 0.8, 1.0)
# Bytes of a TRIANGLE_LIST marker per triangle corner (a float64 point and a float32 RGBA colour), and about those
# of the rest of a marker (header, pose, scale, empty fields).
CORNER_BYTES = 3 * 8 + 4 * 4
MARKER_BYTES = 200


class InvalidMeshError(ValueError):
    """Mesh arrays or marker parameters are inconsistent."""


@dataclass(frozen=True)
class TriangleBlock:
    """The content of one TRIANGLE_LIST marker."""

    corners: np.ndarray  # (3T, 3) float64: triangle corners, three consecutive rows per triangle
    colors: Optional[np.ndarray]  # (3T, 4) float32 RGBA in [0, 1] per corner, or None for the default colour


# ------------------------------------------------------------------------------------------------ geometry


def select_triangles(num_faces: int, triangle_budget: int) -> np.ndarray:
    """Indices of the faces to draw: all of them, or `triangle_budget` evenly spaced ones."""
    if num_faces <= triangle_budget:
        return np.arange(num_faces)
    return np.floor(np.arange(triangle_budget) * (num_faces / triangle_budget)).astype(np.int64)


def triangle_blocks(
    vertices: np.ndarray,
    faces: np.ndarray,
    colors: Optional[np.ndarray],
    max_triangles_per_marker: int = 65536,
    triangle_budget: int = 300_000,
) -> list[TriangleBlock]:
    """Split the (budgeted) mesh into blocks of at most `max_triangles_per_marker` triangles."""
    vertices, faces, colors = _validated_mesh(vertices, faces, colors)
    if max_triangles_per_marker < 1 or triangle_budget < 1:
        raise InvalidMeshError(
            f"max_triangles_per_marker and triangle_budget must be >= 1, got {max_triangles_per_marker} and "
            f"{triangle_budget}"
        )
    kept = faces[select_triangles(len(faces), triangle_budget)]
    corners = vertices[kept].reshape(-1, 3)
    corner_colors = None if colors is None else _rgba_float(colors)[kept].reshape(-1, 4)
    blocks = []
    for first in range(0, len(kept), max_triangles_per_marker):
        rows = slice(3 * first, 3 * min(first + max_triangles_per_marker, len(kept)))
        blocks.append(TriangleBlock(corners[rows], None if corner_colors is None else corner_colors[rows]))
    return blocks


def _validated_mesh(
    vertices: Any, faces: Any, colors: Any
) -> tuple[np.ndarray, np.ndarray, Optional[np.ndarray]]:
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise InvalidMeshError(f"vertices must have shape (V, 3), got {vertices.shape}")
    if faces.size == 0:
        faces = np.zeros((0, 3), dtype=np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise InvalidMeshError(f"faces must be an integer array of shape (F, 3), got {faces.shape} {faces.dtype}")
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise InvalidMeshError(
            f"faces index vertices {faces.min()}..{faces.max()} but there are only {len(vertices)} vertices"
        )
    if not np.all(np.isfinite(vertices)):
        raise InvalidMeshError("vertices contain NaN or inf; remove them before publishing the mesh")
    if colors is not None:
        colors = np.asarray(colors)
        if colors.shape not in ((len(vertices), 3), (len(vertices), 4)) or colors.dtype != np.uint8:
            raise InvalidMeshError(
                f"colors must be uint8 of shape ({len(vertices)}, 3) or ({len(vertices)}, 4), one per vertex, "
                f"got {colors.shape} {colors.dtype}"
            )
    return vertices, faces.astype(np.int64, copy=False), colors


def _rgba_float(colors: np.ndarray) -> np.ndarray:
    """uint8 RGB(A) -> float32 RGBA in [0, 1], opaque when no alpha is given."""
    rgba = np.ones((len(colors), 4), dtype=np.float32)
    rgba[:, : colors.shape[1]] = colors.astype(np.float32) / 255.0
    return rgba


# ------------------------------------------------------------------------------------------------ CDR bytes


def _write_marker(
    w: CdrWriter,
    header: Header,
    ns: str,
    marker_id: int,
    marker_type: int,
    action: int,
    color: tuple[float, float, float, float],
    block: Optional[TriangleBlock],
) -> None:
    """One visualization_msgs/Marker, fields in the order of Marker.msg (Jazzy)."""
    w.time(header.stamp)
    w.string(header.frame_id)
    w.string(ns)
    w.primitives("i", marker_id, marker_type, action)
    w.primitives("d", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)  # pose: identity (position, quaternion xyzw)
    w.primitives("d", 1.0, 1.0, 1.0)  # scale
    w.primitives("f", *color)
    w.time(Time())  # lifetime 0 = forever
    w.primitives("?", False)  # frame_locked
    w.sequence(np.zeros((0, 3), "<f8") if block is None else block.corners.astype("<f8", copy=False), 8)
    no_colors = block is None or block.colors is None
    w.sequence(np.zeros((0, 4), "<f4") if no_colors else block.colors.astype("<f4", copy=False), 4)
    w.string("")  # texture_resource
    w.time(Time())  # texture: CompressedImage header stamp, frame_id, format, data
    w.string("")
    w.string("")
    w.sequence(np.zeros((0, 1), np.uint8), 1)
    w.sequence(np.zeros((0, 2), "<f4"), 4)  # uv_coordinates
    w.string("")  # text
    w.string("")  # mesh_resource
    w.string("")  # mesh_file: filename, data
    w.sequence(np.zeros((0, 1), np.uint8), 1)
    w.primitives("?", False)  # mesh_use_embedded_materials


def serialize_mesh_marker_array(
    vertices: np.ndarray,
    faces: np.ndarray,
    colors: Optional[np.ndarray],
    frame_id: str,
    stamp: Stamp,
    ns: str = "mesh",
    max_triangles_per_marker: int = 65536,
    triangle_budget: int = 300_000,
) -> bytes:
    """CDR bytes of the MarkerArray that `mesh_to_marker_array` returns; publish them with `publisher.publish`."""
    blocks = triangle_blocks(vertices, faces, colors, max_triangles_per_marker, triangle_budget)
    header = Header(stamp=to_time(stamp), frame_id=str(frame_id))
    w = CdrWriter()
    w.primitives("I", 1 + len(blocks))
    _write_marker(w, header, ns, 0, Marker.TRIANGLE_LIST, Marker.DELETEALL, (0.0, 0.0, 0.0, 0.0), None)
    for marker_id, block in enumerate(blocks):
        color = (1.0, 1.0, 1.0, 1.0) if block.colors is not None else DEFAULT_MESH_COLOR
        _write_marker(w, header, ns, marker_id, Marker.TRIANGLE_LIST, Marker.ADD, color, block)
    return w.getvalue()


def block_marker_id(key: tuple[int, int, int]) -> int:
    """The marker id of map block (i, j, k): 10 bits per coordinate (two's complement), so two blocks share an id
    only if they are a multiple of 1024 blocks apart (a kilometre at 1 m blocks)."""
    i, j, k = (int(c) & 0x3FF for c in key)
    return (i << 20) | (j << 10) | k


def block_marker(key: tuple, ns: str) -> tuple[str, int]:
    """The namespace and id of the marker of map block (i, j, k), or (submap, i, j, k) with submaps: each submap's
    blocks in a namespace of their own (a checkbox each in RViz), "<ns>/submap_<n>"."""
    if len(key) == 4:
        return f"{ns}/submap_{int(key[0])}", block_marker_id(key[1:])
    return ns, block_marker_id(key)


def block_message_parts(blocks: Mapping[tuple[int, int, int], TriangleBlock],
                        max_bytes: int) -> list[dict[tuple[int, int, int], TriangleBlock]]:
    """`blocks` cut into consecutive parts of at most about `max_bytes` of message each (a block larger than that
    is a part of its own); one empty part when there are no blocks."""
    parts: list[dict] = [{}]
    size = 0
    for key, block in blocks.items():
        block_bytes = MARKER_BYTES + CORNER_BYTES * len(block.corners)
        if parts[-1] and size + block_bytes > max_bytes:
            parts.append({})
            size = 0
        parts[-1][key] = block
        size += block_bytes
    return parts


def serialize_block_markers(
    blocks: Mapping[tuple[int, int, int], TriangleBlock],
    removed: Iterable[tuple[int, int, int]],
    frame_id: str,
    stamp: Stamp,
    ns: str = "mesh",
    delete_all: bool = False,
) -> bytes:
    """CDR bytes of a MarkerArray for map blocks (`block_marker`): a DELETEALL of `ns` first if `delete_all` (a new
    map), a DELETE for each block in `removed`, and an ADD (a TRIANGLE_LIST replacing any earlier marker of that
    id) for each of `blocks`."""
    header = Header(stamp=to_time(stamp), frame_id=str(frame_id))
    removed = list(removed)
    w = CdrWriter()
    w.primitives("I", int(delete_all) + len(removed) + len(blocks))
    if delete_all:
        _write_marker(w, header, ns, 0, Marker.TRIANGLE_LIST, Marker.DELETEALL, (0.0, 0.0, 0.0, 0.0), None)
    for key in removed:
        _write_marker(w, header, *block_marker(key, ns), Marker.TRIANGLE_LIST, Marker.DELETE, (0.0, 0.0, 0.0, 0.0),
                      None)
    for key, block in blocks.items():
        color = (1.0, 1.0, 1.0, 1.0) if block.colors is not None else DEFAULT_MESH_COLOR
        _write_marker(w, header, *block_marker(key, ns), Marker.TRIANGLE_LIST, Marker.ADD, color, block)
    return w.getvalue()


# ------------------------------------------------------------------------------------------------ message objects


def mesh_to_marker_array(
    vertices: np.ndarray,
    faces: np.ndarray,
    colors: Optional[np.ndarray],
    frame_id: str,
    stamp: Stamp,
    ns: str = "mesh",
    max_triangles_per_marker: int = 65536,
    triangle_budget: int = 300_000,
) -> MarkerArray:
    """The mesh as a MarkerArray message object (slow for large meshes: use serialize_mesh_marker_array)."""
    blocks = triangle_blocks(vertices, faces, colors, max_triangles_per_marker, triangle_budget)
    header = Header(stamp=to_time(stamp), frame_id=str(frame_id))
    delete_all = Marker(header=header, ns=ns, id=0, type=Marker.TRIANGLE_LIST, action=Marker.DELETEALL)
    delete_all.pose.orientation.w = 1.0
    delete_all.scale = Vector3(x=1.0, y=1.0, z=1.0)
    markers = [delete_all]
    for marker_id, block in enumerate(blocks):
        color = (1.0, 1.0, 1.0, 1.0) if block.colors is not None else DEFAULT_MESH_COLOR
        marker = Marker(
            header=header,
            ns=ns,
            id=marker_id,
            type=Marker.TRIANGLE_LIST,
            action=Marker.ADD,
            pose=Pose(),
            scale=Vector3(x=1.0, y=1.0, z=1.0),
            color=ColorRGBA(r=color[0], g=color[1], b=color[2], a=color[3]),
        )
        marker.points = [Point(x=x, y=y, z=z) for x, y, z in block.corners.tolist()]
        if block.colors is not None:
            marker.colors = [ColorRGBA(r=r, g=g, b=b, a=a) for r, g, b, a in block.colors.tolist()]
        markers.append(marker)
    return MarkerArray(markers=markers)
