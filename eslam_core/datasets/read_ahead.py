"""Reading a data set's frames ahead of their use, on CPU time that nothing else wants.

An offline run through the two-process runtime decodes every PNG in the parent process (about 7 ms a 640 x 480
frame pair here), on the same two cores as tracking and mapping. Cores do fall idle in such a run: the tracker waits
for the map's warm-up and, offline, for a mapper that is `runtime.max_keyframe_lag` keyframes behind; the mapper's
small tensors keep only about 1.2 cores busy with both threads. A thread at Linux's SCHED_IDLE policy (`cpu.
lower_priority`) decodes the next frames in that time, so that the parent takes them decoded later, when the cores
are busy. A frame the thread has not read yet (or is still reading) the caller reads itself: the caller never
waits for the low-priority thread, which a busy machine may not run for a long time.
"""
from __future__ import annotations

import threading
from typing import Optional

from eslam_core.cpu import lower_priority
from eslam_core.datasets.base import Frame, RGBDDataset


class ReadAhead:
    """`dataset[i]` for increasing `i` (one caller), with up to `capacity` frames beyond the last one taken read
    ahead (from the first one taken on: a run's set-up is not the time to decode its frames)."""

    def __init__(self, dataset: RGBDDataset, capacity: int):
        if capacity < 1:
            raise ValueError(f"read-ahead capacity must be >= 1 frame, got {capacity}")
        self.dataset, self.capacity = dataset, capacity
        self._ready: dict[int, Frame] = {}
        self._next = 0  # the next frame the thread reads
        self._taken = 0  # frames before this one were handed out (or skipped)
        self._closed = False
        self._cond = threading.Condition()
        self.read_ahead = 0  # frames handed out that the thread had read
        self._thread = threading.Thread(target=self._run, name="eslam-read-ahead", daemon=True)

    @property
    def ready(self) -> int:
        """Frames read ahead and not taken yet."""
        with self._cond:
            return len(self._ready)

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, i: int) -> Frame:
        with self._cond:
            frame = self._ready.pop(i, None)
            self._taken = max(self._taken, i + 1)
            self._next = max(self._next, self._taken)
            for stale in [k for k in self._ready if k < self._taken]:
                del self._ready[stale]
            self._cond.notify()
        # Started once the first frame is claimed: started before, it could read that frame itself first (CI, a
        # loaded machine), a race the caller's own read of the first frame does not have.
        if self._thread.ident is None and not self._closed:
            self._thread.start()
        if frame is None:
            return self.dataset[i]
        self.read_ahead += 1
        return frame

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._ready.clear()
            self._cond.notify()

    def __enter__(self) -> "ReadAhead":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _run(self) -> None:
        lower_priority(19, threading.get_native_id())
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._closed or self._next - self._taken < self.capacity)
                if self._closed or self._next >= len(self.dataset):
                    return
                i = self._next
                self._next += 1
            frame = self._read(i)
            with self._cond:
                if frame is not None and i >= self._taken and not self._closed:
                    self._ready[i] = frame

    def _read(self, i: int) -> Optional[Frame]:
        try:
            return self.dataset[i]
        except Exception:  # noqa: BLE001 - the caller reads this frame again and reports the error itself
            return None
