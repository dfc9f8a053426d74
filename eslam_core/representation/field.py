"""The scene representation: geometry and appearance feature planes with their decoders.

phi_g(p) = h_g(f_g(p)) is the TSDF (positive in free space, 1 at the truncation distance), phi_a(p) = h_a(f_a(p))
the raw colour. `beta` is the learnable sharpness of the SDF-to-density conversion used by the renderer.

A field lives on one device (`run.device`); it takes query points from anywhere and answers on its own device.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from eslam_core.config import ModelConfig
from eslam_core.representation.decoders import Decoder
from eslam_core.representation.planes import FeaturePlanes


class RadianceField(Protocol):
    """What the renderer needs of a scene: TSDF, colour, sharpness and the box where the scene lives."""

    beta: torch.Tensor
    bound_min: torch.Tensor
    bound_max: torch.Tensor

    def sdf(self, points: torch.Tensor) -> torch.Tensor: ...

    def color(self, points: torch.Tensor) -> torch.Tensor: ...


class SceneField(nn.Module):
    def __init__(self, bound: np.ndarray, cfg: ModelConfig, device: torch.device | str | None = None):
        super().__init__()
        self.bound = np.asarray(bound, dtype=np.float64)
        self.geometry_planes = FeaturePlanes(self.bound, (cfg.coarse_resolution, cfg.fine_geometry_resolution),
                                             cfg.channels, cfg.plane_init_std, device)
        self.appearance_planes = FeaturePlanes(self.bound, (cfg.coarse_resolution, cfg.fine_appearance_resolution),
                                               cfg.channels, cfg.plane_init_std, device)
        # Initialised on the host (as the planes): the same seed gives the same decoders on any device.
        self.geometry_decoder = Decoder(self.geometry_planes.out_dim, cfg.decoder_hidden, cfg.decoder_layers, 1,
                                        "tanh").to(device)
        self.appearance_decoder = Decoder(
            self.appearance_planes.out_dim, cfg.decoder_hidden, cfg.decoder_layers, 3, "sigmoid").to(device)
        self.beta = nn.Parameter(torch.tensor(float(cfg.beta_init), device=device), requires_grad=cfg.learn_beta)

    @property
    def device(self) -> torch.device:
        return self.geometry_planes.table.device

    @property
    def bound_min(self) -> torch.Tensor:
        return self.geometry_planes.bound_min

    @property
    def bound_max(self) -> torch.Tensor:
        return self.geometry_planes.bound_min + self.geometry_planes.bound_extent

    def sdf(self, points: torch.Tensor) -> torch.Tensor:
        """(N, 3) -> (N,) normalised TSDF."""
        return self.geometry_decoder(self.geometry_planes(points.to(self.device))).squeeze(-1)

    def color(self, points: torch.Tensor) -> torch.Tensor:
        """(N, 3) -> (N, 3) raw colour in [0, 1]."""
        return self.appearance_decoder(self.appearance_planes(points.to(self.device)))

    def forward(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.sdf(points), self.color(points)

    def grown(self, bound: np.ndarray) -> "SceneField":
        """The field over a larger bound (see FeaturePlanes.grown); decoders and sharpness are shared as they are."""
        new = SceneField.__new__(SceneField)
        nn.Module.__init__(new)
        new.bound = np.asarray(bound, dtype=np.float64)
        new.geometry_planes = self.geometry_planes.grown(new.bound)
        new.appearance_planes = self.appearance_planes.grown(new.bound)
        new.geometry_decoder, new.appearance_decoder, new.beta = \
            self.geometry_decoder, self.appearance_decoder, self.beta
        return new

    def nbytes(self) -> int:
        return sum(p.numel() * p.element_size() for p in self.parameters())

    def plane_parameters(self) -> list[nn.Parameter]:
        return [self.geometry_planes.table, self.appearance_planes.table]

    def decoder_parameters(self) -> list[nn.Parameter]:
        params = list(self.geometry_decoder.parameters()) + list(self.appearance_decoder.parameters())
        return params + ([self.beta] if self.beta.requires_grad else [])

    def parameter_count(self) -> int:
        return sum(p.numel() for p in self.parameters())


class FrozenField:
    """The field as a tracker sees it: the map is fixed, so no gradient flows into it, and each decoder's first
    layer is folded into its feature planes.

    The first layer's pre-activation W_1 f(p) + b_1 is linear in the plane table (f is bilinear weights times table
    rows, summed over planes and concatenated over scales), so W_1 can be applied to every table row once, scale by
    scale, instead of to every sample: a sample then gathers `decoder_hidden` (16) channels per corner instead of
    2 x 32 and no per-sample feature vector is written or back-propagated. Same values as the field up to float
    rounding. The folded tables are built on first use (a few ms), so a tracker that never asks for colour never
    folds the appearance planes; the field must not change while its FrozenField is in use (trackers keep one per
    map version: FoldedMap).
    """

    def __init__(self, field: SceneField):
        self.beta = field.beta.detach()
        self.bound_min, self.bound_max = field.bound_min, field.bound_max
        self._parts = {"sdf": (field.geometry_planes, field.geometry_decoder),
                       "color": (field.appearance_planes, field.appearance_decoder)}
        self._folded: dict[str, tuple] = {}
        self._packed_layers: dict[str, tuple] = {}

    def _fold(self, which: str) -> tuple:
        """(folded table, first-layer bias, [(weight, bias) of the later layers]), built on first use."""
        if which not in self._folded:
            planes, decoder = self._parts[which]
            linears = [m for m in decoder.mlp if isinstance(m, nn.Linear)]
            with torch.no_grad():
                table = planes.project(linears[0].weight)
            self._folded[which] = (table, linears[0].bias.detach(),
                                   [(m.weight.detach(), m.bias.detach()) for m in linears[1:]])
        return self._folded[which]

    def _packed(self, which: str) -> tuple[torch.Tensor, ...]:
        """The layers after the first as the C kernel takes them: widths (in of the first, then each out), weights,
        weights transposed and biases each in one flat tensor."""
        if which not in self._packed_layers:
            _, _, later = self._fold(which)
            dims = [later[0][0].shape[1]] + [w.shape[0] for w, _ in later]
            self._packed_layers[which] = (torch.tensor(dims, dtype=torch.int64),
                                          torch.cat([w.reshape(-1) for w, _ in later]).contiguous(),
                                          torch.cat([w.T.reshape(-1) for w, _ in later]).contiguous(),
                                          torch.cat([b.reshape(-1) for _, b in later]).contiguous())
        return self._packed_layers[which]

    def first_layer(self, which: str, points: torch.Tensor) -> torch.Tensor:
        """(N, 3) -> (N, hidden): the pre-activation W_1 f(p) + b_1 of the "sdf" or "color" decoder."""
        planes = self._parts[which][0]
        table, bias, _ = self._fold(which)
        return planes.lookup(points, table).view(len(points), len(planes.resolutions), -1).sum(1) + bias

    def decode(self, which: str, h: torch.Tensor) -> torch.Tensor:
        """The decoder's layers after the first, on first_layer's output."""
        for weight, bias in self._fold(which)[2]:
            h = F.linear(F.relu(h), weight, bias)
        return self._parts[which][1].activation(h)

    def sdf(self, points: torch.Tensor) -> torch.Tensor:
        return self.decode("sdf", self.first_layer("sdf", points)).squeeze(-1)

    def sdf_with_gradient(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N,) normalised TSDF and its gradient in the points (N, 3), without autograd: a tracker asks for both at
        every iteration, and on a few thousand points building and running autograd's graph of the decoder costs
        more than its arithmetic. One pass of the C kernel where it serves, else the chain rule in torch ops."""
        planes, decoder = self._parts["sdf"]
        table, first_bias, later = self._fold("sdf")
        if decoder.activation_name == "tanh":
            fused = planes.tsdf_with_gradient(points, table, first_bias, *self._packed("sdf"))
            if fused is not None:  # the C kernel: the same in one pass per point
                return fused
        with torch.no_grad():
            h = self.first_layer("sdf", points)
            inputs = []  # each later layer's input before its ReLU
            for weight, bias in later:
                inputs.append(h)
                h = F.linear(F.relu(h), weight, bias)
            y = decoder.activation(h)
            g = decoder.activation_slope(y)  # d y / d h, then back through the layers to the first one's output
            for (weight, _), h_in in zip(reversed(later), reversed(inputs)):
                g = (g @ weight) * (h_in > 0)
        # The first layer's output is the sum over scales of each scale's lookup: the same gradient for each.
        with torch.enable_grad():
            p = points.detach().requires_grad_(True)
            (grad,) = torch.autograd.grad(planes.lookup(p, table), p, g.repeat(1, len(planes.resolutions)))
        return y.squeeze(-1), grad

    def color(self, points: torch.Tensor) -> torch.Tensor:
        return self.decode("color", self.first_layer("color", points))


class FoldedMap:
    """A tracker's FrozenField of the map, kept from frame to frame while the map's version stays the same: folding
    costs a pass over every plane row (0.8 ms a frame on a 9 MB map, 12 ms on a 75 MB one, one core), tracking a
    frame reads a few thousand rows, and the map changes once per mapping step, not per frame."""

    def __init__(self):
        self._of: tuple = (None, None)  # (field, version) of `_frozen`
        self._frozen: FrozenField | None = None

    def of(self, field: SceneField, version: int | None) -> FrozenField:
        """The FrozenField of `field` at `version` (None: unknown, folded afresh)."""
        held, held_version = self._of
        if version is None or held is not field or held_version != version or self._frozen is None:
            self._frozen = FrozenField(field)
            self._of = (field, version) if version is not None else (None, None)
        return self._frozen
