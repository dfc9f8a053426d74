"""ROS 2 messages written as CDR bytes with numpy, for the big ones: rclpy builds a message of thousands of
elements one Python object at a time (a nav_msgs/Path of 300 poses took 88 ms of the node's interpreter lock, of
36000 poses 10 s), while a publisher sends serialised bytes as they are."""
from __future__ import annotations

import struct
from typing import Any

import numpy as np

_CDR_LE_HEADER = b"\x00\x01\x00\x00"


class CdrWriter:
    """Little-endian plain CDR (XCDR1), as rmw_fastrtps serialises ROS 2 messages.

    Every primitive is aligned to its own size, counted from the end of the 4-byte encapsulation header. Strings
    are a uint32 length (including the terminating NUL) and the bytes; sequences a uint32 count and the elements.
    """

    def __init__(self) -> None:
        self._chunks: list[bytes] = [_CDR_LE_HEADER]
        self._offset = 0

    def _align(self, size: int) -> None:
        padding = -self._offset % size
        if padding:
            self._raw(b"\x00" * padding)

    def _raw(self, data: Any) -> None:
        """Bytes, or any C-contiguous buffer (kept by reference until getvalue: the big arrays are copied once)."""
        view = memoryview(data)
        self._chunks.append(view)
        self._offset += view.nbytes

    def primitives(self, fmt: str, *values: Any) -> None:
        """Values of one primitive type (struct format letter, e.g. 'd', 'f', 'i', 'I', '?')."""
        self._align(struct.calcsize(fmt))
        self._raw(struct.pack(f"<{len(values)}{fmt}", *values))

    def string(self, text: str) -> None:
        encoded = text.encode("utf-8")
        self.primitives("I", len(encoded) + 1)
        self._raw(encoded + b"\x00")

    def structs(self, records: np.ndarray, alignment: int) -> None:
        """Records already laid out as CDR (a numpy structured array), the first aligned to `alignment`."""
        if len(records):
            self._align(alignment)
            self._raw(np.ascontiguousarray(records))

    def sequence(self, elements: np.ndarray, alignment: int) -> None:
        """A sequence of fixed-size structs of one primitive type, given as an (N, fields) array."""
        self.primitives("I", len(elements))
        self.structs(elements, alignment)  # (an empty sequence has no element to align)

    def time(self, stamp: Any) -> None:
        """builtin_interfaces/Time (anything with `sec` and `nanosec`)."""
        self.primitives("i", stamp.sec)
        self.primitives("I", stamp.nanosec)

    def getvalue(self) -> bytes:
        return b"".join(self._chunks)
