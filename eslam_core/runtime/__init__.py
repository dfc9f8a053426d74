"""Running SLAM alongside a camera: the runtime API and its single-process and two-process implementations.

    from eslam_core.runtime import make_runtime
    with make_runtime(cfg, dataset.intrinsics, workers=2, policy="offline") as rt:
        for frame in dataset:
            rt.submit(frame)
            for update in rt.poll():
                ...
    rt.save_checkpoint("run/checkpoint.pt")

See api.py for the API, factory.py for `make_runtime`, inprocess.py (workers=1) and multiprocess.py / workers.py / shared.py (workers=2).
"""
from eslam_core.runtime.api import POLICIES, Health, PoseUpdate, RuntimeCrashed, RuntimeSetupError, SLAMRuntime
from eslam_core.runtime.factory import make_runtime

__all__ = ["POLICIES", "Health", "PoseUpdate", "RuntimeCrashed", "RuntimeSetupError", "SLAMRuntime", "make_runtime"]
