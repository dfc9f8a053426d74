"""Adam on the feature planes, restricted to the rows that the mapping step has touched.

Mapping starts a new Adam every step (as the official implementation does), so the moments of a plane row that no
ray of the step has reached are zero, and dense Adam moves it by lr * 0 / (0 + eps) = 0. Updating only the rows
reached so far in the step (a row once reached keeps moving with its momentum) is therefore the same optimisation
as torch.optim.Adam over the whole table, in the same arithmetic, for a cost that follows the keyframe window
instead of the map's size: zeroing a dense gradient and sweeping Adam over the tables took about 6 ms of a 25 ms
fast-preset iteration on one core (ICL office, bench/speed.py), and grows with the map.

The gradient bypasses autograd's `.grad`: the lookup kernel's backward pass adds it into this optimizer's buffer
and marks the rows it reaches (`FeaturePlanes.row_gradients`, attached for the duration of a step). The buffers
live as long as the planes (a grown map gets new ones); between steps they hold zeros.
"""
from __future__ import annotations

import ctypes
import math
from contextlib import contextmanager
from dataclasses import dataclass

import torch

from eslam_core.cpu import flat_nonzero
from eslam_core.native import pointer
from eslam_core.representation.planes import FeaturePlanes, RowGradients


@dataclass
class _TableState:
    planes: FeaturePlanes
    gradients: RowGradients
    exp_avg: torch.Tensor
    exp_avg_sq: torch.Tensor

    @staticmethod
    def for_planes(planes: FeaturePlanes) -> "_TableState":
        table = planes.table
        return _TableState(planes, RowGradients(torch.zeros_like(table.data),
                                                torch.zeros(len(table), dtype=torch.uint8)),
                           torch.zeros_like(table.data), torch.zeros_like(table.data))


class RowSparseAdam:
    """Kept by the mapper across steps; `fresh(planes, lr)` opens one step's optimizer (new moments), `step()`
    applies one iteration's gradients. Needs the planes' C kernel (`FeaturePlanes.kernel()`)."""

    def __init__(self, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        self.betas, self.eps = betas, eps
        self._states: list[_TableState] = []
        self._lr = 0.0
        self._steps = 0

    @contextmanager
    def fresh(self, planes: list[FeaturePlanes], lr: float):
        kept = {id(s.planes): s for s in self._states}  # (a grown map is new planes: new buffers)
        self._states = [kept.get(id(p)) or _TableState.for_planes(p) for p in planes]
        self._lr, self._steps = lr, 0
        for s in self._states:
            s.planes.row_gradients = s.gradients
        try:
            yield self
        finally:
            for s in self._states:
                s.planes.row_gradients = None
                reached = flat_nonzero(s.gradients.touched)
                for buffer in (s.gradients.grad, s.exp_avg, s.exp_avg_sq):
                    buffer.index_fill_(0, reached, 0.0)
                s.gradients.touched.zero_()

    def step(self) -> None:
        self._steps += 1
        beta1, beta2 = self.betas
        step_size = self._lr / (1.0 - beta1 ** self._steps)
        bias2_sqrt = math.sqrt(1.0 - beta2 ** self._steps)
        for s in self._states:
            table = s.planes.table
            lib = s.planes.kernel()
            reached = flat_nonzero(s.gradients.touched)
            lib.adam_rows(pointer(table.data), pointer(s.gradients.grad), pointer(s.exp_avg),
                          pointer(s.exp_avg_sq), pointer(reached), ctypes.c_int64(len(reached)),
                          ctypes.c_int64(table.shape[1]), ctypes.c_float(step_size), ctypes.c_float(beta1),
                          ctypes.c_float(beta2), ctypes.c_float(self.eps), ctypes.c_float(bias2_sqrt),
                          ctypes.c_int(torch.get_num_threads()))
