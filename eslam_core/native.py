"""Build and load the C kernels (eslam_core/kernels/*.c) with the machine's C compiler, on first use.

The kernels are compiled for this machine's CPU (-march=native: 10-30 % faster than the baseline instruction set),
so the shared library is cached in $ESLAM_CACHE (default ~/.cache/eslam) under a hash of the source, the flags and
the CPU's instruction-set flags: a cache shared by different machines never hands one a library it cannot run.
Without a compiler, or with ESLAM_NATIVE=0, callers fall back to the pure-torch reference implementations (slower,
same results). The kernels serve CPU tensors only: on a GPU the torch implementations run (`kernel_status` says
which is in use and why, for `eslam doctor`).
"""
from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
from functools import lru_cache
from pathlib import Path
from typing import Optional

log = logging.getLogger("eslam")
KERNEL_DIR = Path(__file__).resolve().parent / "kernels"


def cache_dir() -> Path:
    return Path(os.environ.get("ESLAM_CACHE", Path.home() / ".cache" / "eslam"))


CFLAGS = ("-O3", "-march=native", "-fno-math-errno", "-fopenmp", "-shared", "-fPIC")


def cpu_identity() -> str:
    """The CPU's instruction-set flags (Linux), or its architecture and name elsewhere."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("flags", "Features")):
                return line
    except OSError:
        pass
    return f"{platform.machine()} {platform.processor()}"


def _compile(src: Path, out: Path) -> None:
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        raise RuntimeError("no C compiler found (set CC)")
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
        tmp_out = Path(tmp) / out.name
        cmd = [cc, *CFLAGS, "-o", str(tmp_out), str(src), "-lm"]
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed:\n{res.stderr}")
        os.replace(tmp_out, out)  # atomic: concurrent builders never load a half-written library


_unavailable: dict[str, str] = {}  # kernel name -> why load_kernel returned None


def pointer(t) -> ctypes.c_void_p:
    """A (contiguous, CPU) tensor's data as a C pointer argument; None -> NULL."""
    return ctypes.c_void_p(None if t is None else t.data_ptr())


def library_path(name: str) -> Path:
    """Where the library of kernels/<name>.c built for this machine is cached."""
    src = KERNEL_DIR / f"{name}.c"
    digest = hashlib.sha256(src.read_bytes() + " ".join(CFLAGS).encode() + cpu_identity().encode()).hexdigest()[:16]
    return cache_dir() / f"{name}-{digest}.so"


@lru_cache(maxsize=None)
def load_kernel(name: str) -> Optional[ctypes.CDLL]:
    """The compiled library of kernels/<name>.c, or None (logged once) when it cannot be built."""
    if os.environ.get("ESLAM_NATIVE", "1") == "0":
        _unavailable[name] = "switched off by ESLAM_NATIVE=0"
        return None
    lib_path = library_path(name)
    try:
        if not lib_path.exists():
            _compile(KERNEL_DIR / f"{name}.c", lib_path)
        return ctypes.CDLL(str(lib_path))
    except (OSError, RuntimeError) as e:
        _unavailable[name] = str(e).strip().splitlines()[0]
        log.warning("native kernel %s unavailable, using the slower torch implementation: %s", name, e)
        return None


def kernel_status(name: str) -> tuple[bool, str]:
    """(compiled, detail): the library's path, or why the torch implementation is used instead (builds the
    kernel if it is not cached yet)."""
    lib = load_kernel(name)
    if lib is not None:
        return True, str(library_path(name))
    return False, _unavailable.get(name, "unavailable")
