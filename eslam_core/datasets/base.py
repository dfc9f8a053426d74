"""The RGB-D sequence abstraction shared by every data set reader, and the file primitives they use.

A reader parses a data set's index files once (file lists, timestamps, ground-truth poses) into a list of
`FrameFiles`s; images are only read when a frame is asked for. Everything a reader returns follows the
conventions of `eslam_core.camera`: colour uint8 RGB, depth float32 metres with 0 = missing, poses camera-to-world
4x4 in OpenCV axes (None = no ground truth for that frame).
"""
from __future__ import annotations

import copy
import operator
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Optional

import numpy as np
from PIL import Image

from eslam_core.camera import Frame, Intrinsics, register_colour
from eslam_core.geometry import orthonormalize


class DatasetError(ValueError):
    """A data set cannot be read; the message names the file or folder at fault and how to fix it."""


@dataclass(frozen=True)
class FrameFiles:
    """Where one frame lives on disk, and what is known about it without opening its images."""

    timestamp: float
    rgb_path: Path
    depth_path: Path
    pose: Optional[np.ndarray]  # 4x4 camera-to-world (OpenCV axes), None = no ground truth


class RGBDDataset(Sequence):
    """A sequence of registered RGB-D frames read lazily from disk.

    Subclasses (one per data set format) parse their index files in `__init__` and hand the frame list to
    `_setup`; they may override `_read_rgb` / `_read_depth` where their format needs special handling (resizing,
    invalid-depth codes). `subset()` returns a view sharing the parsed records, so it costs nothing.
    """

    kind: ClassVar[str] = ""  # "tum" | "icl" | "replica" | "scannet" | "7scenes"

    root: Path  # the folder the frames are read from (the sequence / scene folder)
    name: str
    intrinsics: Intrinsics  # of the images as returned (colour and depth have the same size)
    depth_scale: float  # raw depth units per metre
    # The colour camera's intrinsics where colour is not registered to depth (7-Scenes): the colour image is then
    # resampled onto the depth camera's pixels as it is read (camera.register_colour), unless `register_colour`
    # is False or the images are not of the size these intrinsics describe (resized copies: the reader cannot know
    # the colour camera then). None: the data set's colour is registered already.
    colour_intrinsics: ClassVar[Optional[Intrinsics]] = None
    register_colour: bool = True

    def __init__(self) -> None:
        # The base class is abstract: only the format readers know how to find their frames.
        if type(self) is RGBDDataset:
            raise TypeError("RGBDDataset is abstract: use open_dataset(path) or a reader such as TUMDataset(path)")

    def _setup(
        self,
        root: Path,
        name: str,
        intrinsics: Intrinsics,
        depth_scale: float,
        records: list[FrameFiles],
        what_was_read: str,
    ) -> None:
        """Store the parsed sequence; `what_was_read` names the index files, for the empty-sequence error."""
        if not records:
            raise empty_sequence_error(root, self.kind, what_was_read)
        if not (np.isfinite(depth_scale) and depth_scale > 0):
            raise DatasetError(f"depth_scale must be a positive number of raw units per metre, got {depth_scale}")
        self.root = root
        self.name = name
        self.intrinsics = intrinsics
        self.depth_scale = float(depth_scale)
        self._records: tuple[FrameFiles, ...] = tuple(records)

    # --- the Sequence interface -------------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._records)

    def __getitem__(self, i: int) -> Frame:  # type: ignore[override]
        n = len(self._records)
        if isinstance(i, slice):
            raise TypeError("use dataset.subset(start, stop, stride) for a range of frames, not a slice")
        position = operator.index(i)
        if position < 0:
            position += n
        if not 0 <= position < n:
            raise IndexError(f"frame index {i} out of range for a sequence of {n} frames")
        record = self._records[position]
        rgb = self._read_rgb(record.rgb_path)
        depth = self._read_depth(record.depth_path)
        self._check_registered(rgb, depth, record)
        colour = self.colour_intrinsics
        if self.register_colour and colour is not None and rgb.shape[:2] == (colour.height, colour.width):
            rgb = register_colour(rgb, depth, self.intrinsics, colour)
        pose = None if record.pose is None else record.pose.copy()
        return Frame(index=position, timestamp=record.timestamp, rgb=rgb, depth=depth, pose=pose)

    def __repr__(self) -> str:
        i = self.intrinsics
        return (
            f"{type(self).__name__}(kind={self.kind!r}, name={self.name!r}, frames={len(self)}, "
            f"{i.width}x{i.height}, root={str(self.root)!r})"
        )

    # --- what is known without reading images -----------------------------------------------------------------

    def timestamps(self) -> np.ndarray:
        """(N,) float64 timestamps in seconds (or frame numbers for data sets without a clock)."""
        return np.array([r.timestamp for r in self._records], dtype=np.float64)

    def gt_poses(self) -> list[Optional[np.ndarray]]:
        """Ground-truth camera-to-world poses (OpenCV axes), None where a frame has none."""
        return [None if r.pose is None else r.pose.copy() for r in self._records]

    @property
    def has_ground_truth(self) -> bool:
        return any(r.pose is not None for r in self._records)

    def subset(self, start: int = 0, stop: Optional[int] = None, stride: int = 1) -> "RGBDDataset":
        """A view of frames start, start+stride, ... before stop (Python slice rules; indices restart at 0)."""
        if int(stride) < 1:
            raise DatasetError(f"subset stride must be a positive integer, got {stride}")
        records = self._records[slice(start, stop, int(stride))]
        if not records:
            raise DatasetError(
                f"subset(start={start}, stop={stop}, stride={stride}) selects no frames of {self.name} "
                f"({len(self)} frames); choose a range inside 0..{len(self)}"
            )
        view = copy.copy(self)
        view._records = records
        return view

    # --- image reading; readers override where their format differs ---------------------------------------

    def _read_rgb(self, path: Path) -> np.ndarray:
        return read_rgb(path)

    def _read_depth(self, path: Path) -> np.ndarray:
        return read_depth_raw(path).astype(np.float32) / np.float32(self.depth_scale)

    def _check_registered(self, rgb: np.ndarray, depth: np.ndarray, record: FrameFiles) -> None:
        """Colour, depth and intrinsics must describe the same pixel grid, or every projection is wrong."""
        if rgb.shape[:2] != depth.shape:
            raise DatasetError(
                f"colour image {record.rgb_path} is {rgb.shape[1]}x{rgb.shape[0]} but depth image "
                f"{record.depth_path} is {depth.shape[1]}x{depth.shape[0]}; register/resize them to the same size"
            )
        w, h = self.intrinsics.width, self.intrinsics.height
        if depth.shape != (h, w):
            raise DatasetError(
                f"depth image {record.depth_path} is {depth.shape[1]}x{depth.shape[0]} but the intrinsics are for "
                f"{w}x{h}; pass intrinsics that match the images (config `camera:` section)"
            )


# --- file primitives ---------------------------------------------------------------------------------------------


def empty_sequence_error(root: Path, kind: str, what_was_read: str) -> DatasetError:
    return DatasetError(
        f"no RGB-D frames found in {root} (looked for {what_was_read}); "
        f"check that the folder holds a complete {kind} sequence"
    )


def require_file(path: Path, what: str, fix: str) -> Path:
    """`path` if it is a file, else a DatasetError naming it."""
    if not path.is_file():
        raise DatasetError(f"missing {what}: {path} not found; {fix}")
    return path


def require_dir(path: Path, what: str, fix: str) -> Path:
    if not path.is_dir():
        raise DatasetError(f"missing {what}: folder {path} not found; {fix}")
    return path


def _open_image(path: Path, what: str) -> Image.Image:
    require_file(path, what, "re-download or re-extract the sequence, or drop the frame from the index file")
    try:
        image = Image.open(path)
        image.load()  # decode now, so a truncated file fails here and not later inside numpy
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as err:
        raise DatasetError(
            f"cannot read {what} {path} ({err}); the file is corrupt or not an image: re-download or re-extract it"
        ) from None
    return image


def read_rgb(path: Path) -> np.ndarray:
    """H x W x 3 uint8 RGB (greyscale or RGBA files are converted)."""
    image = _open_image(path, "colour image")
    return np.asarray(image.convert("RGB"), dtype=np.uint8)


# PIL modes a 16-bit greyscale PNG may open as; "I" (32-bit) is what older Pillow versions used for them.
_SIXTEEN_BIT_MODES = ("I;16", "I;16L", "I;16B", "I;16N")


def read_depth_raw(path: Path) -> np.ndarray:
    """H x W uint16 raw depth units as stored in a 16-bit greyscale image."""
    image = _open_image(path, "depth image")
    raw = np.asarray(image)
    fits_sixteen_bits = image.mode == "I" and raw.size > 0 and raw.min() >= 0 and raw.max() <= 65535
    if image.mode not in _SIXTEEN_BIT_MODES and not fits_sixteen_bits:
        raise DatasetError(
            f"depth image {path} has PIL mode {image.mode!r}, not 16-bit greyscale; depth must be stored as "
            f"uint16 PNG (raw units = metres x depth_scale), e.g. written with PIL mode 'I;16'"
        )
    return raw.astype(np.uint16)


def read_text_rows(path: Path, n_fields: int | tuple[int, ...], what: str) -> list[tuple[int, list[str]]]:
    """(line number, fields) of each non-blank, non-`#` line; any other field count is a DatasetError."""
    counts = (n_fields,) if isinstance(n_fields, int) else n_fields
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise DatasetError(f"missing {what}: {path} not found; check the data set folder") from None
    except (OSError, UnicodeDecodeError) as err:
        raise DatasetError(f"cannot read {what} {path} ({err}); re-download or re-extract it") from None
    rows = []
    for line_number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = stripped.replace(",", " ").split()
        if len(fields) not in counts:
            expected = " or ".join(str(c) for c in counts)
            raise DatasetError(
                f"{path}, line {line_number}: expected {expected} fields in this {what}, got {len(fields)} "
                f"({stripped[:80]!r}); fix or delete the line"
            )
        rows.append((line_number, fields))
    return rows


def parse_floats(fields: list[str], path: Path, line_number: int) -> np.ndarray:
    """The fields as float64, or a DatasetError pointing at the line."""
    try:
        return np.array([float(f) for f in fields], dtype=np.float64)
    except ValueError:
        raise DatasetError(
            f"{path}, line {line_number}: expected numbers, got {' '.join(fields)[:80]!r}; fix or delete the line"
        ) from None


def checked_pose(matrix: np.ndarray, path: Path, line_number: Optional[int] = None) -> Optional[np.ndarray]:
    """A 4x4 camera-to-world pose; None if the data set marks it invalid (non-finite values, as ScanNet does).

    A finite matrix that is not a rigid transform (bottom row not 0 0 0 1, rotation not orthonormal) is an
    error rather than a silent None: it means the file is not what the reader thinks it is. A rotation that is
    orthonormal only to the file's precision (7-Scenes' KinectFusion poses have singular values 0.9998-0.99996)
    is replaced by the nearest rotation, so that relative poses and inverses built from it are rigid.
    """
    where = f"{path}" if line_number is None else f"{path}, line {line_number}"
    matrix = np.asarray(matrix, dtype=np.float64).reshape(4, 4)
    if not np.all(np.isfinite(matrix)):
        return None
    rotation = matrix[:3, :3]
    if (not np.allclose(matrix[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6)
            or not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-3) or np.linalg.det(rotation) < 0):
        raise DatasetError(
            f"{where}: not a rigid camera-to-world transform (rotation must be orthonormal, last row 0 0 0 1); "
            f"check the file is the ground-truth pose file of this data set"
        )
    return orthonormalize(matrix)  # det > 0 was checked: the nearest rotation, not a flipped axis


def read_matrix(path: Path, size: int, what: str) -> np.ndarray:
    """A size x size matrix written as `size` lines of `size` numbers (pose and camera-matrix files)."""
    rows = read_text_rows(path, size, what)
    if len(rows) != size:
        raise DatasetError(
            f"{path}: expected {size} lines of {size} numbers in this {what}, got {len(rows)}; fix the file"
        )
    return np.stack([parse_floats(fields, path, n) for n, fields in rows])


def read_matrix4x4(path: Path, what: str) -> np.ndarray:
    """A 4x4 matrix written as 4 lines of 4 numbers (ScanNet and 7-Scenes pose / intrinsic files)."""
    return read_matrix(path, 4, what)


def intrinsics_from_matrix(matrix: np.ndarray, width: int, height: int, source: Path) -> Intrinsics:
    """Pinhole intrinsics of a 3x3 or 4x4 camera matrix for images of the given size."""
    try:
        return Intrinsics(width, height, fx=float(matrix[0, 0]), fy=float(matrix[1, 1]),
                          cx=float(matrix[0, 2]), cy=float(matrix[1, 2]))
    except ValueError as err:
        raise DatasetError(f"{source} is not a valid camera matrix ({err}); fix or delete the file") from None


def numbered_files(folder: Path, pattern: re.Pattern[str]) -> dict[int, Path]:
    """Frame number -> file, for the files of `folder` whose name matches `pattern` (the number in group 1)."""
    found = {}
    for child in folder.iterdir():
        match = pattern.match(child.name)
        if match:
            found[int(match.group(1))] = child
    return found


def image_size(path: Path, what: str) -> tuple[int, int]:
    """(width, height) from the image header, without decoding pixels."""
    require_file(path, what, "re-download or re-extract the sequence")
    try:
        with Image.open(path) as image:
            return image.size
    except (OSError, SyntaxError, ValueError) as err:
        raise DatasetError(
            f"cannot read {what} {path} ({err}); the file is corrupt: re-download or re-extract it"
        ) from None


def resolve_depth_scale(override: Optional[float], found: Optional[float], default: float) -> float:
    """The `depth_scale` argument wins over a value found in the data set's files, which wins over the default."""
    for value in (override, found):
        if value is not None:
            return float(value)
    return float(default)
