"""Output files written whole or not at all, with one line that says why not.

Every output (trajectory, checkpoint, mesh, config, summary) is written to a temporary file beside its target and
moved over it with os.replace only once complete: an interrupted or failed save leaves the older file of the same
name as it was, and no half-written file behind. A write that fails is reported as an OutputWriteError whose
message is one line that names the file and what to do; on a full disk (or quota) it says so, with the space needed.

torch.save to a path writes through its own C++ file writer, which turns a full disk into a RuntimeError such as
"[enforce fail at inline_container.cc:672] . unexpected pos 9792 vs 9684" without the errno: that error is mapped
here too, and the free space of the file system tells whether the disk was the cause.
"""
from __future__ import annotations

import contextlib
import errno
import os
import shutil
import uuid
from pathlib import Path
from typing import Iterator, Optional, Union

NO_SPACE = (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC))
# What torch's zip writer (caffe2 inline_container.cc) says when a write to its file fails.
TORCH_WRITE_FAILED = ("inline_container", "PytorchStreamWriter", "file write failed")
HINT = "free space or choose another output folder"


class OutputWriteError(OSError):
    """An output that could not be written; str() is one line naming the file, the cause and what to do.

    An OSError, so code that already reports OSErrors from writers reports this one too."""

    def __init__(self, message: str, path: Optional[Path] = None, no_space: bool = False) -> None:
        super().__init__(message)  # (only the message: pickling rebuilds the error from it)
        self.path = None if path is None else Path(path)
        self.no_space = no_space


class OutputsNotWritten(OutputWriteError):
    """Several outputs of one save failed (the others were written): one line per failure in `errors`."""

    def __init__(self, errors: list[OutputWriteError], written: list[Path]) -> None:
        super().__init__("\n".join(str(e) for e in errors), errors[0].path, any(e.no_space for e in errors))
        self.errors, self.written = errors, written


@contextlib.contextmanager
def atomic_output(path: Union[str, Path], size_hint: Optional[int] = None, fsync: bool = True) -> Iterator[Path]:
    """Yields a temporary path beside `path` for the caller to write; on success it replaces `path`.

    On any error the temporary file is removed and `path` is left untouched; an OSError (or torch's failed-write
    RuntimeError) becomes an OutputWriteError. `size_hint`: the bytes the file will take, for the message (the
    size written so far is used without it). `fsync`: flush to the disk before the rename, so that a crash leaves
    the old or the new file, never an empty one, and so that a full disk the page cache hid is seen here."""
    path = Path(path)
    # Hidden and unique: two saves of the same file do not share a temporary, and a folder listing shows no
    # half-written file while it is being written.
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}-{uuid.uuid4().hex[:8]}")
    try:
        yield tmp
        if fsync:
            _fsync(tmp)
        os.replace(tmp, path)
    except BaseException as e:
        error = _as_output_error(e, path, size_hint, _size(tmp))  # before the unlink: the free space at the failure
        with contextlib.suppress(OSError):
            tmp.unlink()
        if error is None:
            raise
        raise error from None
    if fsync:
        _fsync_folder(path.parent)


def write_atomic(path: Union[str, Path], data: Union[bytes, str], fsync: bool = True) -> Path:
    """Write `data` (text as UTF-8) to `path` through atomic_output; returns `path`."""
    path = Path(path)
    raw = data.encode() if isinstance(data, str) else data
    with atomic_output(path, size_hint=len(raw), fsync=fsync) as tmp:
        tmp.write_bytes(raw)
    return path


def no_space_message(path: Path, needed: Optional[int], quota: bool = False) -> str:
    where = _mount_point(path.parent)
    what = f"{where} (disk quota exceeded)" if quota else where
    size = "" if not needed else f" ({_mb(needed)} MB needed)"
    return f"no space left on {what} writing {path}{size}: {HINT}"


def make_output_folder(folder: Union[str, Path]) -> Path:
    """mkdir -p, its failure (a full disk, a read-only place) an OutputWriteError line like a file's."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise _as_output_error(e, folder, None, 0) from None
    return folder


def failure_line(path: Path, error: BaseException) -> str:
    """One line for a save of `path` that raised `error`, whatever the error (for callers that go on)."""
    known = _as_output_error(error, Path(path), None, 0)
    if known is not None:
        return str(known)
    text = str(error).strip().splitlines()
    return f"could not write {path}: {text[0] if text else type(error).__name__}"


def _as_output_error(e: BaseException, path: Path, size_hint: Optional[int],
                     written: int) -> Optional[OutputWriteError]:
    """The OutputWriteError for a failed write of `path` (`written` bytes of it done), None for errors that are
    not about writing (left as they are)."""
    if isinstance(e, OutputWriteError):
        return e
    needed = size_hint if size_hint else (written or None)
    if isinstance(e, OSError):
        if e.errno in NO_SPACE:
            return OutputWriteError(no_space_message(path, needed, e.errno != errno.ENOSPC), path, no_space=True)
        reason = e.strerror or str(e) or type(e).__name__
        return OutputWriteError(f"cannot write {path}: {reason}: choose another output folder", path)
    if isinstance(e, RuntimeError) and any(s in str(e) for s in TORCH_WRITE_FAILED):
        if _disk_full(path.parent, needed, written):
            return OutputWriteError(no_space_message(path, needed), path, no_space=True)
        first = (str(e).strip().splitlines() or [type(e).__name__])[0][:160]
        return OutputWriteError(f"cannot write {path}: torch's writer failed ({first}): choose another output "
                                f"folder", path)
    return None


def _disk_full(folder: Path, needed: Optional[int], written: int) -> bool:
    """Whether the rest of the file would not fit: torch reports a full disk without its errno."""
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return False
    rest = (needed - written) if needed and needed > written else 0
    return free < max(rest, 1 << 20)  # less than a MB left at the failure: the disk filled up


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_folder(folder: Path) -> None:
    # The rename itself is durable once the folder is synced; not every file system allows it, and the file is
    # complete either way.
    with contextlib.suppress(OSError):
        _fsync(folder)


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def _mount_point(folder: Path) -> str:
    p = Path(os.path.abspath(folder))
    try:
        while not os.path.ismount(p) and p.parent != p:
            p = p.parent
    except OSError:
        return str(folder)
    return str(p)


def _mb(n: int) -> str:
    mb = n / 2**20
    return f"about {mb:.0f}" if mb >= 10 else f"about {mb:.1f}" if mb >= 0.1 else "under 0.1"
