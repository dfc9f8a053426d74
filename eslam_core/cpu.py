"""CPU settings for the method's tensor workload.

- `denormals_flushed()`: inside the heavy loops (tracking, mapping) denormal floats are flushed to zero. Gradients
  through saturated sigmoid / tanh (the renderer's density, the TSDF decoder) underflow below 1e-38, where x86
  arithmetic takes a slow path: the decoders' backward matrix products ran several times slower. The flag is per
  thread; torch's switch sets it in the calling thread only, the denormals kernel in the OpenMP pool that torch and
  the plane kernels share. It is switched off again on the way out because other numerical code is not written for
  it (scipy's k-d tree crashed on the evaluation's point clouds with it on).
- `keep_freed_memory()`: glibc keeps freed blocks (up to 1 GB) instead of unmapping them, so the per-iteration
  feature and gradient tensors (10-40 MB) are not page-faulted in again every iteration (allocating and writing a
  40 MB tensor: 9 ms by default, 1.4 ms with freed memory kept). The blocks are reused, so peak memory barely
  changes; freed memory goes back to the system when the process ends, or when a long-running process calls
  `release_freed_memory()` now and then (the runtime's workers do, every `RELEASE_EVERY_S`): blocks freed between
  live ones cannot be trimmed from the heap's top, and over a 20-minute soak they had grown each worker's resident
  memory by 40-75 %.
- `one_thread()`: torch runs the block on one thread. Operations on a few thousand elements (the SDF tracker's
  points) are slower split over threads than on one: the fast tracker took 29 ms a frame on one thread and 42 ms on
  two (ICL, 2-core machine), its matrix products and element-wise ops each paying the hand-off.
- `freeze_start_up_objects()`: a worker's objects from its start (modules, torch's operator registry, the config:
  about 240k) live as long as it does, and each full collection of the garbage collector walked them all: 120 ms on
  this machine, a stall of the whole process in which a live tracker drops the frames behind it. Frozen, they are
  never walked again; a full collection then walks what the run made since (0.002 ms right after the freeze).
  `FullCollections` times the full collections that remain (the runtime's per-stage profile shows them).
- `flat_nonzero(mask)`: the indices of a mask's true elements; torch's nonzero runs 5x slower than numpy's on a CPU
  (a 640 x 480 frame's mask: 1.1 -> 0.2 ms), and the tracker asks once per frame, the plane optimiser twice per
  iteration.

On a GPU run (`run.device: cuda`) the heavy loops run on the device and none of these changes anything there; they
stay on for the little host-side work, where they cost nothing.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import gc
import os
import time
from contextlib import contextmanager

import numpy as np
import torch

from eslam_core.native import load_kernel

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters
PR_SET_NAME = 15  # prctl option
KEEP_BYTES = 1 << 30
_flush_depth = 0  # nesting of denormals_flushed() blocks in this process


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds; False where the C library is not glibc."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"))
        return bool(libc.mallopt(M_MMAP_THRESHOLD, KEEP_BYTES)) and bool(libc.mallopt(M_TRIM_THRESHOLD, KEEP_BYTES))
    except (OSError, AttributeError, TypeError):
        return False


RELEASE_EVERY_S = 30.0


def release_freed_memory() -> bool:
    """Hand the heap's free pages back to the system (glibc's malloc_trim); False where that is not available."""
    try:
        return bool(ctypes.CDLL(ctypes.util.find_library("c")).malloc_trim(0))
    except (OSError, AttributeError, TypeError):
        return False


class PeriodicRelease:
    """`release()` calls release_freed_memory at most every `every_s` seconds (for a worker's main loop)."""

    def __init__(self, every_s: float = RELEASE_EVERY_S):
        self.every_s, self.last = every_s, time.monotonic()

    def release(self) -> None:
        now = time.monotonic()
        if now - self.last >= self.every_s:
            self.last = now
            release_freed_memory()


def freeze_start_up_objects() -> None:
    """Put every object alive now out of the garbage collector's reach (call it once start-up is done)."""
    gc.collect()
    gc.freeze()


class FullCollections:
    """Seconds this process has spent in the garbage collector's full (generation 2) collections, and how many."""

    def __init__(self):
        self.seconds, self.count = 0.0, 0
        self._start: float | None = None
        gc.callbacks.append(self._note)

    def _note(self, phase: str, info: dict) -> None:
        if info["generation"] != 2:
            return
        if phase == "start":
            self._start = time.perf_counter()
        elif self._start is not None:
            self.seconds += time.perf_counter() - self._start
            self.count += 1
            self._start = None

    def close(self) -> None:
        gc.callbacks.remove(self._note)


def lower_priority(nice: int, pid: int = 0) -> None:
    """Give a process (0: this one; on Linux its main thread, whose later threads inherit it; on Linux also a single
    thread, by its `threading.get_native_id()`) the nice value `nice`, where the platform has nice values. Nice 19
    also means Linux's SCHED_IDLE policy: CPU time that no other process wants. A nice-19 process still counts as
    load on its CPU, so a waking mapper was queued behind it on its CPU rather than placed there, and the mesh
    process took a third of a core from the mapper on 2 cores; a CPU that runs only SCHED_IDLE work counts as idle
    when the scheduler places a waking process."""
    try:
        os.setpriority(os.PRIO_PROCESS, pid, nice)
        if nice >= 19 and hasattr(os, "SCHED_IDLE"):
            os.sched_setscheduler(pid, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        pass


def name_process(name: str) -> None:
    """Name this process (Linux: what `top`, `ps -o comm` and /proc/<pid>/comm show; at most 15 characters), so
    that a user and the benchmarks tell the workers apart."""
    try:
        ctypes.CDLL(ctypes.util.find_library("c")).prctl(PR_SET_NAME, name.encode()[:15], 0, 0, 0)
    except (OSError, AttributeError, TypeError):
        pass


def set_flush_denormals(on: bool, threads: int | None = None) -> int:
    """Switch flush-to-zero in this thread and `threads` threads of the OpenMP pool; returns the pool threads set
    (0 without the kernel)."""
    torch.set_flush_denormal(on)
    lib = load_kernel("denormals")
    return int(lib.set_flush_denormals(int(on), threads or torch.get_num_threads())) if lib is not None else 0


@contextmanager
def denormals_flushed():
    """Flush-to-zero on inside the block (also as a decorator), back off when the outermost block ends."""
    global _flush_depth
    threads = torch.get_num_threads()
    if _flush_depth == 0:
        set_flush_denormals(True, threads)
    _flush_depth += 1
    try:
        yield
    finally:
        _flush_depth -= 1
        if _flush_depth == 0:  # every pool thread used meanwhile (the count may change mid-block)
            set_flush_denormals(False, max(threads, torch.get_num_threads()))


@contextmanager
def one_thread():
    """torch on one thread inside the block (also as a decorator); the count before is restored after it."""
    threads = torch.get_num_threads()
    if threads != 1:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        if threads != 1:
            torch.set_num_threads(threads)


def flat_nonzero(mask: torch.Tensor) -> torch.Tensor:
    """(K,) int64 positions of the true elements of a flattened bool / uint8 mask, on the mask's device."""
    if mask.device.type != "cpu":
        return torch.nonzero(mask.reshape(-1)).squeeze(1)
    return torch.from_numpy(np.flatnonzero(mask.numpy()))
