"""`eslam doctor`: what this installation runs on — torch and its CUDA build, the GPUs torch sees, the device
`run.device: auto` picks, whether the fused C kernels are compiled, and the ROS 2 wheels found."""
from __future__ import annotations

import importlib
import importlib.metadata as metadata
import os
import platform
import sys

import torch

import eslam_core
from eslam_core.device import cuda_missing_reason, resolve_device
from eslam_core.native import kernel_status

KERNELS = {"plane_lookup": "feature-plane lookup", "denormals": "denormal flush in the OpenMP pool",
           "photometric": "the SDF tracker's photometric residuals",
           "gauss_newton": "the SDF tracker's normal equations"}
ROS_WHEELS = ("ros-jazzy-rclpy", "ros-jazzy-common-interfaces", "rclpy", "rosbags")  # setup.py's ros extra and bags


def torch_lines() -> list[str]:
    build = f"CUDA {torch.version.cuda}" if torch.version.cuda else "CPU-only build"
    lines = [f"torch {torch.__version__} ({build}), {torch.get_num_threads()} CPU threads"]
    if not torch.cuda.is_available():
        lines.append(f"CUDA: not available ({cuda_missing_reason()})")
        return lines
    lines.append(f"CUDA: {torch.cuda.device_count()} GPU(s)")
    for i in range(torch.cuda.device_count()):
        p = torch.cuda.get_device_properties(i)
        lines.append(f"  cuda:{i}  {p.name}, {p.total_memory / 2**30:.1f} GiB, compute capability {p.major}.{p.minor}")
    return lines


def kernel_lines(device: torch.device) -> list[str]:
    lines = []
    for name, what in KERNELS.items():
        compiled, detail = kernel_status(name)
        state = f"compiled ({detail})" if compiled else f"fallback to plain torch: {detail}"
        lines.append(f"  {name} ({what}): {state}")
    if device.type != "cpu":
        lines.append(f"  (the kernels serve CPU tensors: on {device} the plain-torch lookup runs)")
    return lines


def ros_lines() -> list[str]:
    try:
        rclpy = importlib.import_module("rclpy")
        where = os.path.dirname(getattr(rclpy, "__file__", "") or "")
        lines = [f"  rclpy importable ({where}), ROS_DISTRO={os.environ.get('ROS_DISTRO', 'unset')}"]
    except Exception as e:  # noqa: BLE001 - a broken ROS install raises anything at import; report it
        lines = [f"  rclpy not importable ({type(e).__name__}: {e}); install with pip install -e '.[ros]'"]
    for name in ROS_WHEELS:
        try:
            lines.append(f"    {name} {metadata.version(name)}")
        except metadata.PackageNotFoundError:
            lines.append(f"    {name}: not installed")
    others = sorted({d.metadata["Name"] for d in metadata.distributions()
                     if (d.metadata["Name"] or "").lower().startswith("ros-")} - set(ROS_WHEELS))
    if others:
        lines.append(f"    and {len(others)} more ros-* wheels")
    return lines


def report() -> str:
    """The doctor's report, one fact per line."""
    device = resolve_device("auto")
    lines = [f"eslam {eslam_core.__version__}, Python {platform.python_version()} ({sys.executable}), "
             f"{platform.system()} {platform.machine()}"]
    lines += torch_lines()
    lines.append(f"run.device: auto picks {device} (choose with --device or run.device: auto, cpu, cuda, cuda:N)")
    lines.append("native kernels:")
    lines += kernel_lines(device)
    lines.append("ROS 2 wheels:")
    lines += ros_lines()
    return "\n".join(lines)
