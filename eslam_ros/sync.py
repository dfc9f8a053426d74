"""Approximate-time synchronisation of N message streams (e.g. RGB and depth images).

This reproduces the semantics of the ApproximateTime policy of ROS' C++ `message_filters`, which is not
available here (the Python port in message_filters is greedy and can pair the wrong frames).

Definitions used throughout:
- A *set* is one message per topic. Its *span* is newest stamp - oldest stamp; the best set is the one
  with the smallest span.
- The *pivot* is the topic whose message is the newest in the first valid set found; its stamp is the
  *pivot time*. Every set that can still be formed for this pivot must end at or after the pivot time.
- The *candidate* is the best set found so far for the current pivot. While searching, messages already
  examined are set aside in `past` (they may be needed again if the search is abandoned).
- A candidate is emitted only when no later message can improve it: either every alternative for the pivot
  has been examined, or even the most optimistic future set (starting at the pivot time) would be worse.
  The optimistic bound uses "virtual" moves: an empty queue is assumed to receive its next message at the
  pivot time (or at last stamp + the topic's minimum inter-message interval, if that is later).
- Comparing sets, an age penalty favours emitting old sets: a set (start, end) beats the candidate
  (c_start, c_end) when (end - c_end) * (1 + age_penalty) < start - c_start.

Each message is used in at most one set, sets come out in time order, and messages older than an emitted
set are discarded. Every message that is discarded without being emitted is counted in `dropped`.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any, Optional, Sequence


class SyncConfigError(ValueError):
    """The synchronizer was configured or called with invalid arguments."""


class NonMonotonicStampError(ValueError):
    """A message is older than the previous message on the same topic."""


@dataclass(frozen=True)
class _Stamped:
    stamp: float  # seconds
    msg: Any


class ApproximateTimeSynchronizer:
    """Pairs messages of `n_topics` streams whose stamps are close, as message_filters' ApproximateTime.

    Feed every message with `add(topic_index, stamp, msg)`; it returns the sets (tuples of messages in topic
    order) that this message completed. Call `flush()` at the end of the stream for the last pending set.

    queue_size: per topic, the most messages kept while waiting (the oldest is dropped beyond it).
    max_interval: a set whose span exceeds this many seconds is never emitted (None: no limit).
    age_penalty: >= 0; larger values emit sets sooner at the cost of slightly worse matches.
    inter_message_lower_bounds: per topic, a known minimum time between consecutive messages (seconds,
        default 0). Only used to prove a candidate optimal earlier, which lowers latency.
    """

    def __init__(
        self,
        n_topics: int,
        queue_size: int = 10,
        max_interval: Optional[float] = None,
        age_penalty: float = 0.1,
        *,
        inter_message_lower_bounds: Optional[Sequence[float]] = None,
    ) -> None:
        if not isinstance(n_topics, int) or n_topics < 2:
            raise SyncConfigError(f"n_topics must be an integer >= 2 (one per synchronised stream), got {n_topics!r}")
        if not isinstance(queue_size, int) or queue_size < 1:
            raise SyncConfigError(f"queue_size must be an integer >= 1, got {queue_size!r}")
        if max_interval is not None and not (max_interval >= 0):
            raise SyncConfigError(f"max_interval must be >= 0 seconds or None (no limit), got {max_interval!r}")
        if not (age_penalty >= 0):
            raise SyncConfigError(f"age_penalty must be >= 0, got {age_penalty!r}")
        bounds = [0.0] * n_topics if inter_message_lower_bounds is None else list(map(float, inter_message_lower_bounds))
        if len(bounds) != n_topics or not all(b >= 0 for b in bounds):
            raise SyncConfigError(
                f"inter_message_lower_bounds must hold {n_topics} values >= 0 (seconds), "
                f"got {inter_message_lower_bounds!r}"
            )

        self.n_topics = n_topics
        self.queue_size = queue_size
        self.max_interval = math.inf if max_interval is None else float(max_interval)
        self.age_penalty = float(age_penalty)
        self.inter_message_lower_bounds = bounds
        # Messages discarded per topic without being part of an emitted set.
        self.dropped: list[int] = [0] * n_topics

        self._queues: list[deque[_Stamped]] = [deque() for _ in range(n_topics)]
        self._past: list[list[_Stamped]] = [[] for _ in range(n_topics)]
        self._last_stamp: list[Optional[float]] = [None] * n_topics
        # A topic that overflowed may have lost the partner of another topic's message, so it must not become
        # the pivot until a set is seen in which it is not the newest message.
        self._pivot_forbidden: list[bool] = [False] * n_topics
        # The search for the current pivot (pivot None: no candidate yet).
        self._pivot: Optional[int] = None
        self._pivot_time = 0.0
        self._candidate: Optional[tuple[_Stamped, ...]] = None
        self._candidate_start = 0.0
        self._candidate_end = 0.0

    # ----------------------------------------------------------------------------------------------- public

    def add(self, topic_index: int, stamp: float, msg: Any) -> list[tuple]:
        """Queue `msg` (stamp in seconds) on topic `topic_index`; return the sets it completed, oldest first."""
        if not isinstance(topic_index, int) or not 0 <= topic_index < self.n_topics:
            raise SyncConfigError(f"topic_index must be an integer in [0, {self.n_topics - 1}], got {topic_index!r}")
        stamp = float(stamp)
        if not math.isfinite(stamp):
            raise SyncConfigError(f"topic {topic_index}: stamp must be a finite number of seconds, got {stamp!r}")
        last = self._last_stamp[topic_index]
        if last is not None and stamp < last:
            raise NonMonotonicStampError(
                f"topic {topic_index}: stamp {stamp:.9f} s is older than the previous stamp {last:.9f} s on the same "
                f"topic; skip this message (or call flush() before replaying a new stream)"
            )
        self._last_stamp[topic_index] = stamp

        queue = self._queues[topic_index]
        queue.append(_Stamped(stamp, msg))
        emitted = self._process()

        if len(queue) + len(self._past[topic_index]) > self.queue_size:
            # Abandon the search in progress: it may rely on the message about to be dropped.
            self._restore_past()
            queue.popleft()
            self.dropped[topic_index] += 1
            self._pivot_forbidden[topic_index] = True
            if self._pivot is not None:
                self._reset_candidate()
                emitted += self._process()
        return emitted

    def flush(self) -> list[tuple]:
        """End of stream: emit every set the queued messages still allow, then empty the synchronizer.

        No message will follow, so the pending candidate is already the best its pivot can get. What remains
        after that cannot form a set and is counted as dropped. Afterwards a new stream may start (stamps
        may restart from any value).
        """
        emitted: list[tuple] = []
        while self._pivot is not None:
            emitted.append(self._emit_candidate())
            emitted += self._process()
        for i in range(self.n_topics):
            self.dropped[i] += len(self._queues[i]) + len(self._past[i])
            self._queues[i].clear()
            self._past[i].clear()
            self._pivot_forbidden[i] = False
            self._last_stamp[i] = None
        return emitted

    @property
    def pending(self) -> int:
        """Number of messages held (queued or set aside), waiting for a decision."""
        return sum(len(q) for q in self._queues) + sum(len(p) for p in self._past)

    # --------------------------------------------------------------------------------------------- search

    def _process(self) -> list[tuple]:
        """Advance the search while every topic has a message to examine; return the emitted sets."""
        emitted: list[tuple] = []
        while all(self._queues):
            start_i, start_t = self._oldest_head()
            end_i, end_t = self._newest_head()
            for i in range(self.n_topics):
                if i != end_i:
                    # No message this topic dropped could have made a better set than the heads we see now.
                    self._pivot_forbidden[i] = False

            if self._pivot is None:
                if end_t - start_t > self.max_interval or self._pivot_forbidden[end_i]:
                    self._queues[start_i].popleft()
                    self.dropped[start_i] += 1
                    continue
                self._make_candidate(start_t, end_t)
                self._pivot, self._pivot_time = end_i, end_t
            elif self._beats_candidate(start_t, end_t):
                self._make_candidate(start_t, end_t)  # same pivot, better set
            self._past[start_i].append(self._queues[start_i].popleft())

            if start_i == self._pivot:
                # Every set that contains the pivot's message has been examined.
                emitted.append(self._emit_candidate())
            elif not self._beats_candidate(self._pivot_time, end_t):
                # Any later set must span [pivot time, end_t] or more, already worse than the candidate.
                emitted.append(self._emit_candidate())
            elif not all(self._queues):
                proved = self._prove_optimal_with_virtual_moves()
                if proved is not None:
                    emitted.append(proved)
        return emitted

    def _prove_optimal_with_virtual_moves(self) -> Optional[tuple]:
        """Continue the search optimistically (empty queues get a message at the earliest possible time).

        If even that cannot beat the candidate, emit it and return the set; otherwise undo the moves and
        return None (wait for more messages).
        """
        moves = [0] * self.n_topics
        while True:
            start_i, start_t = self._virtual_boundary(newest=False)
            _, end_t = self._virtual_boundary(newest=True)
            if not self._beats_candidate(self._pivot_time, end_t):
                return self._emit_candidate()  # emitting also restores the virtually moved messages
            if self._beats_candidate(start_t, end_t):
                # An optimistic future set would be better: the candidate is not proven optimal yet.
                for i in range(self.n_topics):
                    for _ in range(moves[i]):
                        self._queues[i].appendleft(self._past[i].pop())
                return None
            # Here start_t < pivot time, so start_i has a real message (empty queues sit at >= pivot time).
            self._past[start_i].append(self._queues[start_i].popleft())
            moves[start_i] += 1

    def _beats_candidate(self, start: float, end: float) -> bool:
        """Whether a set spanning [start, end] is better than the candidate, with the age penalty."""
        return (end - self._candidate_end) * (1.0 + self.age_penalty) < start - self._candidate_start

    # ------------------------------------------------------------------------------------------ bookkeeping

    def _oldest_head(self) -> tuple[int, float]:
        return _boundary([q[0].stamp for q in self._queues], newest=False)

    def _newest_head(self) -> tuple[int, float]:
        return _boundary([q[0].stamp for q in self._queues], newest=True)

    def _virtual_stamp(self, i: int) -> float:
        """Head stamp of topic i, or the earliest stamp its next message can have if its queue is empty."""
        if self._queues[i]:
            return self._queues[i][0].stamp
        earliest = self._past[i][-1].stamp + self.inter_message_lower_bounds[i]
        return max(earliest, self._pivot_time)

    def _virtual_boundary(self, newest: bool) -> tuple[int, float]:
        return _boundary([self._virtual_stamp(i) for i in range(self.n_topics)], newest)

    def _make_candidate(self, start: float, end: float) -> None:
        self._candidate = tuple(q[0] for q in self._queues)
        self._candidate_start, self._candidate_end = start, end
        # Messages set aside before the new candidate are older than it: they can no longer be used.
        for i, past in enumerate(self._past):
            self.dropped[i] += len(past)
            past.clear()

    def _emit_candidate(self) -> tuple:
        candidate = self._candidate
        self._reset_candidate()
        self._restore_past()
        for i, queue in enumerate(self._queues):
            used = queue.popleft()
            assert used is candidate[i], "the candidate's message must be the oldest one held for its topic"
        return tuple(entry.msg for entry in candidate)

    def _restore_past(self) -> None:
        for queue, past in zip(self._queues, self._past):
            queue.extendleft(reversed(past))
            past.clear()

    def _reset_candidate(self) -> None:
        self._pivot, self._pivot_time = None, 0.0
        self._candidate, self._candidate_start, self._candidate_end = None, 0.0, 0.0


def _boundary(stamps: Sequence[float], newest: bool) -> tuple[int, float]:
    """(topic, stamp) of the oldest or newest stamp; ties go to the first topic for the oldest and the last
    topic for the newest, as in message_filters, so that start and end differ when all stamps are equal."""
    best = 0
    for i in range(1, len(stamps)):
        if (stamps[i] >= stamps[best]) if newest else (stamps[i] < stamps[best]):
            best = i
    return best, stamps[best]
