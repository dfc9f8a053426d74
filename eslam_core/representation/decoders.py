"""Shallow MLP decoders h_g (features -> TSDF) and h_a (features -> raw colour) (paper Sec. 3.1)."""
from __future__ import annotations

import torch
from torch import nn


class Decoder(nn.Module):
    """ReLU MLP; `tanh` output gives a TSDF in units of the truncation, `sigmoid` an RGB colour in [0, 1]."""

    def __init__(self, in_dim: int, hidden: int, layers: int, out_dim: int, activation: str):
        super().__init__()
        dims = [in_dim] + [hidden] * layers
        blocks: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:]):
            blocks += [nn.Linear(a, b), nn.ReLU(inplace=True)]
        blocks.append(nn.Linear(dims[-1], out_dim))
        self.mlp = nn.Sequential(*blocks)
        self.activation = {"tanh": torch.tanh, "sigmoid": torch.sigmoid}[activation]
        self.activation_name = activation

    def activation_slope(self, y: torch.Tensor) -> torch.Tensor:
        """d activation / d input, written in the activation's output y."""
        return 1.0 - y * y if self.activation_name == "tanh" else y * (1.0 - y)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.activation(self.mlp(features))
