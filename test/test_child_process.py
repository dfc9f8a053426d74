"""How the parent waits for a child to start (child_process.wait_for_start): a slow child that works is waited for,
a hung one is given up on, a dead one is seen at once."""
import multiprocessing
import os
import time

import pytest

from eslam_core.child_process import cpu_seconds, wait_for_start


def _busy_then_ready(connection, seconds):
    end = time.process_time() + seconds
    while time.process_time() < end:  # work, as importing torch at nice 19 on a busy machine does, only slower
        pass
    connection.send("ready")


def _hang(connection):
    time.sleep(60)


def _spawn(target, *args):
    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe()
    process = ctx.Process(target=target, args=(child,) + args, daemon=True)
    process.start()
    child.close()
    return parent, process


def test_a_child_that_works_longer_than_the_stall_limit_is_waited_for():
    parent, process = _spawn(_busy_then_ready, 2.5)
    try:
        assert wait_for_start(parent, process, stalled_s=1.5, limit_s=60)
        assert parent.recv() == "ready"
    finally:
        process.kill()


def test_a_hung_child_is_given_up_after_the_stall_limit():
    parent, process = _spawn(_hang)
    try:
        started = time.monotonic()
        assert not wait_for_start(parent, process, stalled_s=2.0, limit_s=60)
        assert 2.0 <= time.monotonic() - started < 10
        assert process.is_alive()  # it hung rather than died: the caller says so and stops it
    finally:
        process.kill()


def _exit(connection):
    pass


def test_a_dead_child_is_given_up_at_once():
    parent, process = _spawn(_exit)
    started = time.monotonic()
    assert wait_for_start(parent, process, stalled_s=30, limit_s=60)  # the pipe's end can be read ...
    assert time.monotonic() - started < 15  # (the spawn's own start, then one poll)
    with pytest.raises(EOFError):  # ... and says the child is gone
        parent.recv()


def test_cpu_time_of_a_process():
    before = cpu_seconds(os.getpid())
    end = time.process_time() + 0.2
    while time.process_time() < end:
        pass
    assert cpu_seconds(os.getpid()) - before >= 0.15
    assert cpu_seconds(2**22 + 7) is None  # beyond Linux's largest pid
