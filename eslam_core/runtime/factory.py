"""`make_runtime`: the runtime for a number of workers, tuned by the config's `runtime` section."""
from __future__ import annotations

import dataclasses
from typing import Optional

from eslam_core.camera import Intrinsics
from eslam_core.config import Config
from eslam_core.runtime.api import RuntimeSetupError, SLAMRuntime, check_policy
from eslam_core.runtime.inprocess import InProcessRuntime
from eslam_core.runtime.multiprocess import MultiProcessRuntime

IMPLEMENTATIONS = {1: InProcessRuntime, 2: MultiProcessRuntime}
WORKER_CHOICES = tuple(IMPLEMENTATIONS)


def make_runtime(cfg: Config, intrinsics: Intrinsics, workers: int = 2, policy: str = "offline", *,
                 threads: Optional[int] = None, checkpoint: Optional[str] = None, **tuning) -> SLAMRuntime:
    """A runtime for frames of `intrinsics` (the camera as the frames arrive, before `camera.image_scale`).

    workers=1: lock-step SLAM on a background thread; workers=2: tracking and mapping processes. `threads`: torch
    threads per worker (default: `run.threads` from the config, or the machine's cores split between the workers).
    The implementation's tuning is the config's `runtime` section, which it reads itself; `tuning` overrides
    fields of that section (`capacity=4`, `catch_up_iterations=40`). `checkpoint`: a saved map to start from. Call
    `start()` (or use it as a context manager) before submitting frames.
    """
    check_policy(policy)
    Runtime = IMPLEMENTATIONS.get(workers)
    if Runtime is None:
        raise RuntimeSetupError(f"workers must be one of {WORKER_CHOICES} (1 = lock-step in this process, 2 = a "
                                f"tracking and a mapping process), got {workers!r}")
    return Runtime(tuned(cfg, tuning), intrinsics, policy=policy, threads=threads, checkpoint=checkpoint)


def tuned(cfg: Config, tuning: dict) -> Config:
    """`cfg` with fields of its runtime section replaced, checked as the config's own are."""
    fields = [f.name for f in dataclasses.fields(cfg.runtime)]
    unknown = sorted(set(tuning) - set(fields))
    if unknown:
        raise RuntimeSetupError(f"make_runtime: {unknown[0]!r} is not a runtime setting; the settings are the fields "
                                f"of the config's runtime section: {', '.join(fields)}")
    runtime = dataclasses.replace(cfg.runtime, **tuning)
    problems: list[str] = []
    runtime.validate(lambda ok, key, why: ok or problems.append(f"{key} {why}"))
    if problems:
        raise RuntimeSetupError(f"make_runtime: {problems[0]}")
    return dataclasses.replace(cfg, runtime=runtime)
