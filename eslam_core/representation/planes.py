"""Multi-scale axis-aligned feature planes (paper Sec. 3.1).

A field (geometry or appearance) has three planes (xy, xz, yz) at a coarse and a fine scale. The feature of a point
is the bilinear interpolation on each plane, summed over the three planes of a scale and concatenated over the two
scales: f(p) = [F_xy^c(p) + F_xz^c(p) + F_yz^c(p) ; F_xy^f(p) + F_xz^f(p) + F_yz^f(p)].

All six planes of a field are stored as one table of feature rows (one row per plane cell, `channels` columns).
The lookup equals grid_sample with align_corners=True and border padding on each plane. It runs as one fused C
kernel (kernels/plane_lookup.c) whose backward gives the gradients of the table and of the point positions (which
tracking needs). `reference_lookup` is the same computation in plain torch (an `embedding_bag` over bags of 3 planes
x 4 bilinear corners): the fallback without a C compiler, the reference the kernel is tested against, and the path
on a GPU (the kernel serves CPU tensors only).

With the kernel, the table's gradient can go to `row_gradients` (a buffer and the rows it reached) instead of
autograd's `.grad`: mapping's row-sparse Adam (mapping/plane_adam.py) updates only those rows.
"""
from __future__ import annotations

from dataclasses import dataclass

import ctypes

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from eslam_core.native import load_kernel, pointer

PLANE_AXES = ((0, 1), (0, 2), (1, 2))  # xy, xz, yz: (column axis, row axis) of each plane


@dataclass(frozen=True)
class PlaneLayout:
    """Where each plane of each scale lives in the shared table."""

    sizes: tuple  # per scale: number of grid points along x, y, z
    offsets: tuple  # per scale, per plane: first row of that plane in the table
    rows: int

    @staticmethod
    def for_bound(bound: np.ndarray, resolutions: tuple[float, ...]) -> "PlaneLayout":
        extent = bound[1] - bound[0]
        sizes, offsets, row = [], [], 0
        for res in resolutions:
            n = tuple(int(max(2, round(e / res) + 1)) for e in extent)
            sizes.append(n)
            scale_offsets = []
            for a, b in PLANE_AXES:
                scale_offsets.append(row)
                row += n[a] * n[b]
            offsets.append(tuple(scale_offsets))
        return PlaneLayout(tuple(sizes), tuple(offsets), row)


def bilinear_bags(points: torch.Tensor, bound_min: torch.Tensor, bound_extent: torch.Tensor,
                  layout: PlaneLayout, grid_sizes: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Table rows and bilinear weights of every point: (N * scales, 12) indices and weights.

    Coordinates are clamped to the bound (border padding), so points outside read the border features.
    `grid_sizes`: layout.sizes as a (scales, 3) tensor on the points' device, if the caller keeps one (made here
    otherwise: on a GPU that is a host-to-device copy, which waits for the queued work).
    """
    unit = ((points - bound_min) / bound_extent).clamp(0.0, 1.0)  # (N, 3) in [0, 1]
    if grid_sizes is None:
        grid_sizes = torch.tensor(layout.sizes, dtype=points.dtype, device=points.device)
    all_idx, all_w = [], []
    for n, offsets, sizes in zip(layout.sizes, layout.offsets, grid_sizes.to(points.dtype)):
        g = unit * (sizes - 1)  # grid coordinates, align_corners=True
        base = torch.minimum(g.detach().floor(), sizes - 2)  # lower corner; keeps the upper corner in range
        frac = g - base  # differentiable in the point position
        base = base.long()
        idx_s, w_s = [], []
        for (a, b), off in zip(PLANE_AXES, offsets):
            i0, j0 = base[:, a], base[:, b]
            fa, fb = frac[:, a], frac[:, b]
            row0 = off + j0 * n[a] + i0  # plane stored row-major: row index along axis b, column along axis a
            idx_s.append(torch.stack([row0, row0 + 1, row0 + n[a], row0 + n[a] + 1], dim=-1))
            w_s.append(torch.stack([(1 - fa) * (1 - fb), fa * (1 - fb), (1 - fa) * fb, fa * fb], dim=-1))
        all_idx.append(torch.cat(idx_s, dim=-1))
        all_w.append(torch.cat(w_s, dim=-1))
    # (N, scales, 12) -> (N * scales, 12): bag k of point i is row i * scales + k, so the output reshapes to
    # (N, scales * channels) = the concatenation over scales.
    idx = torch.stack(all_idx, dim=1).reshape(-1, 12)
    w = torch.stack(all_w, dim=1).reshape(-1, 12)
    return idx, w


def reference_lookup(points: torch.Tensor, table: torch.Tensor, bound_min: torch.Tensor, bound_extent: torch.Tensor,
                     layout: PlaneLayout, grid_sizes: torch.Tensor | None = None) -> torch.Tensor:
    """(N, 3) points -> (N, scales * channels) features, in plain torch (any device)."""
    idx, w = bilinear_bags(points, bound_min, bound_extent, layout, grid_sizes)
    return F.embedding_bag(idx, table, per_sample_weights=w, mode="sum").reshape(len(points), -1)


def _cpu_float32(t: torch.Tensor) -> bool:
    return t.device.type == "cpu" and t.dtype == torch.float32


@dataclass
class RowGradients:
    """Where the kernel's backward pass accumulates a table's gradient instead of autograd's `.grad`: `grad`
    (rows, channels), added to, and `touched` (rows,) uint8, set to 1 on every row the gradient reached."""

    grad: torch.Tensor
    touched: torch.Tensor


class _FusedLookup(torch.autograd.Function):
    @staticmethod
    def forward(ctx, points, table, sizes, offsets, bound_min, bound_extent, lib, sink):
        points = points.contiguous()
        n, channels = len(points), table.shape[1]
        scales = len(sizes) // 3
        out = torch.empty(n, scales * channels)
        threads = torch.get_num_threads()
        lib.plane_forward(pointer(points), ctypes.c_int64(n), pointer(table), ctypes.c_int64(channels),
                          ctypes.c_int64(scales), pointer(sizes), pointer(offsets), pointer(bound_min),
                          pointer(bound_extent), pointer(out), ctypes.c_int(threads))
        ctx.save_for_backward(points, table, sizes, offsets, bound_min, bound_extent)
        ctx.lib, ctx.sink = lib, sink
        return out

    @staticmethod
    def backward(ctx, grad_out):
        points, table, sizes, offsets, bound_min, bound_extent = ctx.saved_tensors
        grad_out = grad_out.contiguous()
        n, channels = len(points), table.shape[1]
        scales = len(sizes) // 3
        threads = ctypes.c_int(torch.get_num_threads())
        common = (ctypes.c_int64(scales), pointer(sizes), pointer(offsets), pointer(bound_min),
                  pointer(bound_extent), pointer(grad_out))
        grad_points = grad_table = None
        if ctx.needs_input_grad[0]:
            grad_points = torch.zeros_like(points)
            ctx.lib.plane_backward_points(pointer(points), ctypes.c_int64(n), pointer(table),
                                          ctypes.c_int64(channels), *common, pointer(grad_points), threads)
        if ctx.needs_input_grad[1]:  # into autograd's gradient, or added to the row gradients attached
            sink = ctx.sink
            target = torch.zeros_like(table) if sink is None else sink.grad
            ctx.lib.plane_backward_table(pointer(points), ctypes.c_int64(n), ctypes.c_int64(table.shape[0]),
                                         ctypes.c_int64(channels), *common, pointer(target),
                                         pointer(None if sink is None else sink.touched), threads)
            grad_table = target if sink is None else None
        return grad_points, grad_table, None, None, None, None, None, None


class FeaturePlanes(nn.Module):
    """The coarse and fine xy / xz / yz planes of one field, as a single table of feature rows."""

    def __init__(self, bound: np.ndarray, resolutions: tuple[float, ...], channels: int, init_std: float,
                 device: torch.device | str | None = None):
        super().__init__()
        self.layout = PlaneLayout.for_bound(bound, resolutions)
        self.resolutions = tuple(resolutions)
        self.channels = channels
        self.init_std = init_std
        # Drawn on the host whatever the device: the same seed gives the same initial map on a CPU and a GPU.
        self.table = nn.Parameter((torch.randn(self.layout.rows, channels) * init_std).to(device))
        self.register_buffer("bound_min", torch.tensor(bound[0], dtype=torch.float32, device=device))
        self.register_buffer("bound_extent", torch.tensor(bound[1] - bound[0], dtype=torch.float32, device=device))
        # The grid sizes on the planes' device for the torch path (not part of the map's state: the layout is).
        self.register_buffer("grid_sizes", torch.tensor(self.layout.sizes, dtype=torch.float32, device=device),
                             persistent=False)
        # The C kernel's arguments (host memory: the kernel serves CPU tensors only).
        self._sizes = torch.tensor([v for n in self.layout.sizes for v in n], dtype=torch.int64)
        self._offsets = torch.tensor([v for o in self.layout.offsets for v in o], dtype=torch.int64)
        self.use_native = True
        self.row_gradients: RowGradients | None = None  # set by mapping's row-sparse Adam while it runs

    def __getstate__(self):
        # An optimiser's working buffers, not part of the map: a snapshot taken in the middle of a mapping step
        # (the mesh's, a checkpoint's) leaves them out.
        return {**super().__getstate__(), "row_gradients": None}

    @property
    def out_dim(self) -> int:
        return self.channels * len(self.resolutions)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """(N, 3) world points -> (N, scales * channels) features."""
        return self.lookup(points, self.table)

    def kernel(self) -> ctypes.CDLL | None:
        """The C kernel library when lookups on this table run in it (CPU, float32, kernel built), else None."""
        return load_kernel("plane_lookup") if self.use_native and _cpu_float32(self.table) else None

    def lookup(self, points: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
        """The lookup on any table of this layout (rows, any number of channels): (N, scales * table channels)."""
        lib = self.kernel() if _cpu_float32(points) and _cpu_float32(table) else None
        if lib is None:
            return reference_lookup(points, table, self.bound_min, self.bound_extent, self.layout, self.grid_sizes)
        sink = self.row_gradients if table is self.table else None
        return _FusedLookup.apply(points, table, self._sizes, self._offsets, self.bound_min, self.bound_extent, lib,
                                  sink)

    def tsdf_with_gradient(self, points: torch.Tensor, table: torch.Tensor, bias: torch.Tensor, dims: torch.Tensor,
                           weights: torch.Tensor, weights_t: torch.Tensor, biases: torch.Tensor
                           ) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The TSDF decoder on a table folded with its first layer (`bias`: that layer's), its later layers packed
        (`dims` (layers + 1,) int64; `weights`, the same transposed and `biases` each flat, layer after layer) and
        tanh, with the gradient in the points, in one pass of the C kernel: (N,), (N, 3). None where the kernel
        cannot serve (no kernel, not CPU float32, layers beyond its limits): the caller computes it with torch."""
        tensors = (points, table, bias, weights, weights_t, biases)
        lib = self.kernel() if all(_cpu_float32(t) for t in tensors) else None
        if lib is None:
            return None
        points = points.contiguous()
        sdf, grad = torch.empty(len(points)), torch.empty(len(points), 3)
        status = lib.tsdf_with_gradient(
            pointer(points), ctypes.c_int64(len(points)), pointer(table), ctypes.c_int64(table.shape[1]),
            ctypes.c_int64(len(self.resolutions)), pointer(self._sizes), pointer(self._offsets),
            pointer(self.bound_min), pointer(self.bound_extent), pointer(bias), ctypes.c_int64(len(dims) - 1),
            pointer(dims), pointer(weights), pointer(weights_t), pointer(biases), pointer(sdf), pointer(grad),
            ctypes.c_int(torch.get_num_threads()))
        return (sdf, grad) if status == 0 else None

    def project(self, weight: torch.Tensor) -> torch.Tensor:
        """The table with each scale's rows multiplied by that scale's block of `weight` (out, scales * channels),
        a linear layer applied to the features: (rows, out). lookup(p, project(W)) summed over scales = W f(p)."""
        starts = [offsets[0] for offsets in self.layout.offsets] + [self.layout.rows]
        blocks = weight.split(self.channels, dim=1)
        return torch.cat([self.table[a:b] @ w.T for a, b, w in zip(starts[:-1], starts[1:], blocks)])

    def grown(self, bound: np.ndarray) -> "FeaturePlanes":
        """The planes over a larger `bound` whose grid points include this one's (grown by whole cells of every
        scale): existing features stay where they are in the world, new cells are initialised as at creation."""
        old_min = self.bound_min.double().cpu().numpy()
        new = FeaturePlanes(bound, self.resolutions, self.channels, self.init_std, device=self.table.device)
        with torch.no_grad():
            for s, res in enumerate(self.resolutions):
                shift = np.round((old_min - np.asarray(bound[0])) / res).astype(int)
                if (shift < 0).any():
                    raise ValueError("FeaturePlanes.grown: the new bound must contain the old one")
                for which, (a, b) in enumerate(PLANE_AXES):
                    new.plane_rows(s, which)[shift[b]: shift[b] + self.layout.sizes[s][b],
                                             shift[a]: shift[a] + self.layout.sizes[s][a]] = self.plane_rows(s, which)
        new.use_native = self.use_native
        return new

    def plane_rows(self, scale: int, which: int) -> torch.Tensor:
        """One plane as a (rows along its second axis, columns along its first, channels) view of the table."""
        a, b = PLANE_AXES[which]
        n = self.layout.sizes[scale]
        off = self.layout.offsets[scale][which]
        return self.table.data[off: off + n[a] * n[b]].view(n[b], n[a], self.channels)

    def plane(self, scale: int, which: int) -> torch.Tensor:
        """One plane as a (channels, rows, cols) image (for inspection and tests)."""
        a, b = PLANE_AXES[which]
        n = self.layout.sizes[scale]
        off = self.layout.offsets[scale][which]
        return self.table[off: off + n[a] * n[b]].reshape(n[b], n[a], self.channels).permute(2, 0, 1)
