"""The pipelined mapper's budget: how many iterations a mapping step gets, when it ends early, and how many
keyframes may wait for a step of their own. A pure policy of counts; the mapper worker says how many newer
keyframes wait (received, or still in the queue).

- Offline, a step runs `mapping.iterations`, as in the lock-step schedule (the tracker waits for the mapper).
- Live, with `idle_iterations`, a step goes on past `mapping.iterations` into the mapper's idle time, and ends there
  once a newer keyframe waits.
- With `catch_up_iterations`, a step ends once newer keyframes wait and it has had its share of that budget, the
  budget divided among the keyframes waiting: a mapper that has fallen behind by several keyframes catches up
  instead of lagging further behind with every step.
- `backlog`: keyframes that may wait beyond the newest before the older ones join the newest's window instead of
  getting a step of their own (0 live; None, unlimited, offline by default).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional


@dataclass(frozen=True)
class MappingBudget:
    iterations: int  # mapping.iterations
    live: bool
    idle_iterations: Optional[int] = None
    catch_up_iterations: Optional[int] = None
    backlog: Optional[int] = None

    @staticmethod
    def of(iterations: int, live: bool, idle_iterations: Optional[int], catch_up_iterations: Optional[int],
           keyframe_backlog: Optional[int]) -> "MappingBudget":
        return MappingBudget(iterations, live, idle_iterations, catch_up_iterations, 0 if live else keyframe_backlog)

    def step_iterations(self) -> Optional[int]:
        """A step's iteration count if not `mapping.iterations` (None)."""
        if self.live and self.idle_iterations is not None:
            return max(self.idle_iterations, self.iterations)
        return None

    def behind(self, done: int, waiting: int) -> bool:
        """Newer keyframes wait and the step has had its share of the catch-up budget."""
        return bool(self.catch_up_iterations) and waiting > 0 and done * waiting >= self.catch_up_iterations

    def stop_early(self, done: int, waiting: int) -> bool:
        """Whether a step that has done `done` iterations ends now, with `waiting` newer keyframes."""
        return self.behind(done, waiting) or (done >= self.iterations and waiting > 0)

    def merged(self, pending: int) -> int:
        """Of `pending` keyframes received and not mapped, how many older ones join the newest's window now."""
        return 0 if self.backlog is None else max(0, pending - self.backlog - 1)
