"""Frames that arrive while the SLAM runtime starts (seconds, when it spawns its worker processes).

The offline policy promises every frame, so they are all kept, up to a byte budget (`start_queue_bytes`; a
640x480 frame is 2.1 MB: 0.9 MB colour, 1.2 MB depth); only beyond it the oldest is dropped, and counted. The
live policy tracks the newest frame anyway, so it keeps the newest `live_frames` of them.
"""
from __future__ import annotations

from collections import deque
from typing import Any, Generic, TypeVar

Item = TypeVar("Item")
LIVE_FRAMES = 30


def frame_bytes(frame: Any) -> int:
    """Memory a queued eslam_core Frame holds (its images)."""
    return int(frame.rgb.nbytes + frame.depth.nbytes)


class StartQueue(Generic[Item]):
    """A FIFO bounded by bytes (offline) or by count (live); `dropped` counts what fell out."""

    def __init__(self, policy: str, budget_bytes: int, live_frames: int = LIVE_FRAMES) -> None:
        self.policy = policy
        self.budget_bytes = budget_bytes
        self.live_frames = live_frames
        self._items: deque[tuple[Item, int]] = deque()
        self.bytes = 0
        self.peak_bytes = 0
        self.dropped = 0

    def __len__(self) -> int:
        return len(self._items)

    def push(self, item: Item, size: int) -> int:
        """Queue `item` (of `size` bytes); returns how many older items were dropped to make room."""
        self._items.append((item, size))
        self.bytes += size
        dropped = 0
        while len(self._items) > 1 and self._over():
            _, old = self._items.popleft()
            self.bytes -= old
            dropped += 1
        if self._over():  # a single frame larger than the whole budget
            self._items.pop()
            self.bytes -= size
            dropped += 1
        self.dropped += dropped
        self.peak_bytes = max(self.peak_bytes, self.bytes)
        return dropped

    def _over(self) -> bool:
        if self.policy == "live":
            return len(self._items) > self.live_frames
        return self.bytes > self.budget_bytes

    def has_room(self, size: int) -> bool:
        """Another frame of `size` bytes would be kept without dropping one (what `ready` reports)."""
        if self.policy == "live":
            return len(self._items) < self.live_frames
        return self.bytes + size <= self.budget_bytes

    def popleft(self) -> Item:
        item, size = self._items.popleft()
        self.bytes -= size
        return item

    def clear(self) -> None:
        self._items.clear()
        self.bytes = 0
