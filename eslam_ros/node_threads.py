"""How the node runs its work: the executor and its turns, a gate around callbacks, periodic threads, the stop
request of a signal, and throttled logging."""
from __future__ import annotations

import threading
import time
from typing import Any, Callable, Optional

from rclpy.exceptions import InvalidHandle
from rclpy.executors import MultiThreadedExecutor


class LogThrottle:
    """At most one log line per key every `period` seconds."""

    def __init__(self, period: float) -> None:
        self.period = period
        self._last: dict[str, float] = {}

    def allow(self, key: str, now: Optional[float] = None) -> bool:
        now = time.monotonic() if now is None else now
        last = self._last.get(key)
        if last is not None and now - last < self.period:
            return False
        self._last[key] = now
        return True


class CallbackGate:
    """Counts the node's callbacks in progress, so that shutdown can wait for them, and turns new ones away once
    closed. (rclpy's MultiThreadedExecutor.shutdown does not wait for callbacks running on its threads.)

    An exception escaping a callback would stop the executor, and with it the node: the gate hands it to
    `on_error` instead.
    """

    def __init__(self, on_error: Callable[[BaseException], None]) -> None:
        self._condition = threading.Condition()
        self._running = 0
        self._on_error = on_error
        self.closed = False

    def wrap(self, callback: Callable[..., Any], when_closed: Optional[Callable[..., Any]] = None) -> Callable:
        def gated(*args: Any) -> Any:
            with self._condition:
                if self.closed:
                    return when_closed(*args) if when_closed else None
                self._running += 1
            try:
                return callback(*args)
            except Exception as error:  # noqa: BLE001 - reported, and the node goes on (or stops, if SLAM died)
                self._on_error(error)
                return when_closed(*args) if when_closed else None
            finally:
                with self._condition:
                    self._running -= 1
                    self._condition.notify_all()

        return gated

    def close(self, timeout: float) -> bool:
        """Refuse new callbacks; True once none is running (False if `timeout` seconds passed first)."""
        with self._condition:
            self.closed = True
            return self._condition.wait_for(lambda: self._running == 0, timeout)


class PeriodicThread:
    """Calls `body` every `period` seconds (0: again at once; the body then waits itself) on a thread of its
    own, until stopped."""

    def __init__(self, name: str, period: float, body: Callable[[], Any]) -> None:
        self._stop = threading.Event()
        self._period, self._body = period, body
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self._period):
            self._body()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join()


class StopRequest:
    """SIGINT / SIGTERM: the first asks the spin loop to stop and save; a second one abandons the saving."""

    def __init__(self) -> None:
        self.requested = False

    def __call__(self, signum: int, frame: Any) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True


def node_executor() -> Any:
    """rclpy's EventsExecutor where this rclpy has it, else a MultiThreadedExecutor. The node measured 40 % of a
    core in the MultiThreadedExecutor's own Python bookkeeping (a wait set rebuilt at every wake-up, several per
    image) against 27 % in all with the EventsExecutor (docs/ros.md). It runs every callback on one thread, so the
    node keeps what may take long off it: poses and the mesh have threads of their own."""
    try:
        from rclpy.experimental import EventsExecutor
    except ImportError:
        return MultiThreadedExecutor(num_threads=2)
    return EventsExecutor()


def spin_once(executor: Any, timeout_sec: float) -> None:
    """One turn of `executor`, through rclpy's race with entities destroyed on another thread (rclpy issue 1142):
    a lifecycle transition, run on an executor thread, removes the node's subscriptions while this thread builds
    its wait set from them; rclpy then raises InvalidHandle from `spin_once`, and the next wait set no longer holds
    them. Left uncaught, deactivating the node stopped its executor."""
    try:
        executor.spin_once(timeout_sec=timeout_sec)
    except InvalidHandle:
        pass
