"""The scene representation: geometry and appearance feature planes with their decoders.

phi_g(p) = h_g(f_g(p)) is the TSDF (positive in free space, 1 at the truncation distance), phi_a(p) = h_a(f_a(p))
the raw colour. `beta` is the learnable sharpness of the SDF-to-density conversion used by the renderer.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np
import torch
from torch import nn

from .config import ModelConfig
from .decoders import Decoder
from .planes import FeaturePlanes


class RadianceField(Protocol):
    """What the renderer needs of a scene: TSDF, colour, sharpness and the box where the scene lives."""

    beta: torch.Tensor
    bound_min: torch.Tensor
    bound_max: torch.Tensor

    def sdf(self, points: torch.Tensor) -> torch.Tensor: ...

    def color(self, points: torch.Tensor) -> torch.Tensor: ...


class SceneField(nn.Module):
    def __init__(self, bound: np.ndarray, cfg: ModelConfig):
        super().__init__()
        self.bound = np.asarray(bound, dtype=np.float64)
        self.geometry_planes = FeaturePlanes(
            self.bound, (cfg.coarse_resolution, cfg.fine_geometry_resolution), cfg.channels, cfg.plane_init_std)
        self.appearance_planes = FeaturePlanes(
            self.bound, (cfg.coarse_resolution, cfg.fine_appearance_resolution), cfg.channels, cfg.plane_init_std)
        self.geometry_decoder = Decoder(self.geometry_planes.out_dim, cfg.decoder_hidden, cfg.decoder_layers, 1, "tanh")
        self.appearance_decoder = Decoder(
            self.appearance_planes.out_dim, cfg.decoder_hidden, cfg.decoder_layers, 3, "sigmoid")
        self.beta = nn.Parameter(torch.tensor(float(cfg.beta_init)), requires_grad=cfg.learn_beta)

    @property
    def bound_min(self) -> torch.Tensor:
        return self.geometry_planes.bound_min

    @property
    def bound_max(self) -> torch.Tensor:
        return self.geometry_planes.bound_min + self.geometry_planes.bound_extent

    def sdf(self, points: torch.Tensor) -> torch.Tensor:
        """(N, 3) -> (N,) normalised TSDF."""
        return self.geometry_decoder(self.geometry_planes(points)).squeeze(-1)

    def color(self, points: torch.Tensor) -> torch.Tensor:
        """(N, 3) -> (N, 3) raw colour in [0, 1]."""
        return self.appearance_decoder(self.appearance_planes(points))

    def forward(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.sdf(points), self.color(points)

    def plane_parameters(self) -> list[nn.Parameter]:
        return [self.geometry_planes.table, self.appearance_planes.table]

    def decoder_parameters(self) -> list[nn.Parameter]:
        params = list(self.geometry_decoder.parameters()) + list(self.appearance_decoder.parameters())
        return params + ([self.beta] if self.beta.requires_grad else [])

    def parameter_count(self) -> int:
        return sum(p.numel() for p in self.parameters())
