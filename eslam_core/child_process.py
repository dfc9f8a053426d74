"""What every child process of the system does about its parent: the tracker and the mapper (runtime/workers.py)
and the mesher (runtime/mesher.py), and how the parent waits for one to start.

A child ignores the stop signals: Ctrl-C reaches the whole process group and service managers send SIGTERM to every
process of a service, but stopping is the parent's decision (it asks its children, or SIGKILLs them). The parent
spawns them with those signals blocked (`spawned_with_stop_signals_blocked`), so that none can hit a child before
it ignores them. A child dies with its parent, even a SIGKILLed one.
"""
from __future__ import annotations

import ctypes
import os
import signal
import threading
import time
from contextlib import contextmanager

from eslam_core.cpu import name_process

STOP_SIGNALS = {signal.SIGINT, signal.SIGTERM}
EXIT_ORPHANED = 3  # the exit code of a child whose parent disappeared
PARENT_WATCH_S = 0.25


@contextmanager
def spawned_with_stop_signals_blocked():
    """Start child processes inside: they inherit the calling thread's signal mask."""
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def die_with_parent(parent_pid: int) -> None:
    """Exit when the parent does, even if it is SIGKILLed: the kernel's parent-death signal where there is one
    (Linux), and in any case a thread that watches the parent pid (a pipe alone would not tell a process blocked
    in recv)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        PR_SET_PDEATHSIG = 1
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent_pid:  # the parent died before the signal was armed
        os._exit(EXIT_ORPHANED)

    def watch() -> None:
        while True:
            time.sleep(PARENT_WATCH_S)
            if os.getppid() != parent_pid:
                os._exit(EXIT_ORPHANED)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def become_child(name: str, parent_pid: int) -> None:
    """The first lines of a child process: ignore the stop signals (then unblock them), die with the parent, and
    show as `eslam-<name>` in ps and top."""
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
    die_with_parent(parent_pid)
    name_process(f"eslam-{name}")


def cpu_seconds(pid: int) -> float | None:
    """The CPU time a process has used (user + system), None where it cannot be read (not Linux, or gone)."""
    try:
        fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def wait_for_start(connection, process, stalled_s: float, limit_s: float) -> bool:
    """Whether the child's first message can be read (or its end: a child that died closed the pipe, and reading
    raises EOFError); False where it made no progress (used no CPU time) for `stalled_s` while starting, or took
    `limit_s` in all.

    Progress, not a fixed deadline: a child spawned at a low priority (the mesher, at nice 19) imports torch in
    seconds on an idle machine but can take minutes where the tracker and the mapper keep both cores busy, and
    a slow start is no reason to take the service down; a hung one is. Where CPU time cannot be read, `stalled_s`
    is a plain deadline."""
    started = time.monotonic()
    last_cpu, last_progress = cpu_seconds(process.pid), started
    while time.monotonic() - started < limit_s:
        if connection.poll(1.0):
            return True
        if not process.is_alive():
            return False
        now, cpu = time.monotonic(), cpu_seconds(process.pid)
        if cpu is not None and last_cpu is not None and cpu > last_cpu:
            last_cpu, last_progress = cpu, now
        elif now - last_progress > stalled_s:
            return False
    return False
