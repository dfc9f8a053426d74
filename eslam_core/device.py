"""Where the method's tensors live: `run.device` (auto | cpu | cuda | cuda:N) resolved to a torch device.

The map (the field's planes, decoders, observed space) is created on the resolved device, and tracking, mapping and
rendering work on the device of the map they are given. Host memory keeps what is large and touched a little at a
time: frames as read, the keyframe store, trajectories. Those cross to the device in batches (`upload`), and
results that leave the method (poses, losses) come back once per frame or mapping step, not per iteration.
"""
from __future__ import annotations

import re
from typing import Optional

import torch

CHOICES = "auto, cpu, cuda or cuda:N"
_SPEC = re.compile(r"^(auto|cpu|cuda)(?::(\d+))?$")


def cuda_missing_reason() -> str:
    """Why torch sees no CUDA GPU, in words a user can act on."""
    if torch.version.cuda is None:
        return f"torch {torch.__version__} is a CPU-only build"
    return f"torch {torch.__version__} (CUDA {torch.version.cuda}) finds no GPU (no driver, or no device visible)"


def device_problem(spec: str) -> Optional[str]:
    """None when `spec` names a device this machine has; else what is wrong and how to fix it (one line)."""
    m = _SPEC.match(str(spec))
    if m is None or (m.group(2) is not None and m.group(1) != "cuda"):
        return f"must be {CHOICES} (N = the GPU's index), got {spec!r}"
    if m.group(1) != "cuda":
        return None
    if not torch.cuda.is_available():
        return (f"{spec!r} asks for a CUDA GPU but {cuda_missing_reason()}: use auto or cpu (--device cpu), or "
                f"install torch's CUDA build (README, 'Using a GPU')")
    index, count = int(m.group(2) or 0), torch.cuda.device_count()
    if index >= count:
        return f"{spec!r} asks for GPU {index} but torch sees {count} (cuda:0 to cuda:{count - 1}); pick one of them"
    return None


def resolve_device(spec: str = "auto") -> torch.device:
    """The torch device of a `run.device` value: `auto` is the first CUDA GPU when torch sees one, else the CPU."""
    problem = device_problem(spec)
    if problem is not None:
        raise ValueError(f"device {problem}")
    if spec == "auto":
        return torch.device("cuda", 0) if torch.cuda.is_available() else torch.device("cpu")
    if spec == "cuda":
        return torch.device("cuda", 0)
    return torch.device(spec)


def upload(t: torch.Tensor, device: torch.device) -> torch.Tensor:
    """A host tensor on `device`, without making the host wait for the device's queued work (a plain copy from
    pageable memory would): staged through pinned memory, whose allocator keeps it until the copy is done."""
    if t.device == device or device.type != "cuda":
        return t.to(device)
    return t.pin_memory().to(device, non_blocking=True)


def synchronize(device: torch.device) -> None:
    """Wait until the device has done the work queued so far (CUDA runs asynchronously; the CPU has nothing to
    wait for). Needed before another process may read what that work wrote."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def peak_memory_mb(device: torch.device) -> float:
    """The device memory this process's tensors took at most (0 on the CPU: see the process's RSS instead)."""
    if device.type != "cuda":
        return 0.0
    return torch.cuda.max_memory_allocated(device) / 2**20
