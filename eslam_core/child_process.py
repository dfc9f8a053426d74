"""What every child process of the system does about its parent: the tracker and the mapper (runtime/workers.py)
and the mesher (runtime/mesher.py).

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
