"""`make_runtime`: the runtime for a number of workers, tuned by the config's `runtime` section."""
from __future__ import annotations

import inspect
from dataclasses import asdict
from typing import Optional

from eslam_core.camera import Intrinsics
from eslam_core.config import Config
from eslam_core.runtime.api import RuntimeSetupError, SLAMRuntime, check_policy
from eslam_core.runtime.inprocess import InProcessRuntime
from eslam_core.runtime.multiprocess import MultiProcessRuntime

IMPLEMENTATIONS = {1: InProcessRuntime, 2: MultiProcessRuntime}
WORKER_CHOICES = tuple(IMPLEMENTATIONS)


def make_runtime(cfg: Config, intrinsics: Intrinsics, workers: int = 2, policy: str = "offline", *,
                 threads: Optional[int] = None, **options) -> SLAMRuntime:
    """A runtime for frames of `intrinsics` (the camera as the frames arrive, before `camera.image_scale`).

    workers=1: lock-step SLAM on a background thread; workers=2: tracking and mapping processes. `threads`: torch
    threads per worker (default: `run.threads` from the config, or the machine's cores split between the workers).
    The implementation's tuning comes from the config's `runtime` section (`capacity` for both; for workers=2
    `publish_every`, `lend_threads`, `keyframe_backlog`, `catch_up_iterations`); `options` override it. Call
    `start()` (or use it as a context manager) before submitting frames.
    """
    check_policy(policy)
    Runtime = IMPLEMENTATIONS.get(workers)
    if Runtime is None:
        raise RuntimeSetupError(f"workers must be one of {WORKER_CHOICES} (1 = lock-step in this process, 2 = a "
                                f"tracking and a mapping process), got {workers!r}")
    accepted = inspect.signature(Runtime.__init__).parameters
    tuning = {k: v for k, v in asdict(cfg.runtime).items() if k in accepted}
    try:
        return Runtime(cfg, intrinsics, policy=policy, threads=threads, **{**tuning, **options})
    except TypeError as e:
        raise RuntimeSetupError(f"make_runtime(workers={workers}): {e}; the options are the keyword arguments of "
                                f"{Runtime.__name__}") from None
