"""Image decoders: rendered image (any size) -> message logits (B, N)."""

from __future__ import annotations

import torch
from torch import nn

from .blocks import ConvBNReLU


class HiddenDecoder(nn.Module):
    """HiDDeN's decoder as in the seed: `blocks` conv-BN-ReLU blocks, the last two with stride 2, global
    average pooling, a linear layer to N bits. CPU-sized variants: `stem_stride` 2 or 4 makes the first
    one or two blocks stride 2 as well, and `growth` 2 doubles the width at each of the last two blocks.
    `head_grid` g > 0 pools to g x g cells instead of one and reads all cells with the linear layer: the
    head keeps coarse position, for view ranges narrow enough that a bit lands in about the same place
    of the framed picture every time (the seed's protocol)."""

    def __init__(self, n_bits: int, channels: int = 64, blocks: int = 7, stem_stride: int = 1,
                 growth: int = 1, head_grid: int = 0):
        super().__init__()
        if stem_stride not in (1, 2, 4):
            raise ValueError("decoder_stem_stride must be 1, 2 or 4")
        stem_blocks = {1: 0, 2: 1, 4: 2}[stem_stride]
        layers, in_channels = [], 3
        for index in range(blocks):
            stride = 2 if index >= blocks - 2 or index < stem_blocks else 1
            out_channels = channels * (growth ** max(0, index - (blocks - 3)))
            if index == 0 and stem_blocks == 2:
                out_channels = max(8, channels // 2)
            layers.append(ConvBNReLU(in_channels, out_channels, stride=stride))
            in_channels = out_channels
        self.features = nn.Sequential(*layers)
        self.head_grid = head_grid
        self.head = nn.Linear(in_channels * max(1, head_grid) ** 2, n_bits)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        features = self.features(image)
        if self.head_grid:
            return self.head(nn.functional.adaptive_avg_pool2d(features, self.head_grid).flatten(1))
        return self.head(features.mean(dim=(2, 3)))


class SimpleCNNDecoder(nn.Module):
    """The seed's baseline: 4 plain conv layers (stride 2), global pooling, linear."""

    def __init__(self, n_bits: int, channels: int = 64):
        super().__init__()
        self.features = nn.Sequential(*[ConvBNReLU(3 if i == 0 else channels, channels, stride=2) for i in range(4)])
        self.head = nn.Linear(channels, n_bits)

    def forward(self, image):
        return self.head(self.features(image).mean(dim=(2, 3)))


class _Residual(nn.Module):
    def __init__(self, in_channels: int, channels: int):
        super().__init__()
        self.body = nn.Sequential(ConvBNReLU(in_channels, channels, stride=2),
                                  nn.Conv2d(channels, channels, 3, padding=1, bias=False), nn.BatchNorm2d(channels))
        self.skip = nn.Conv2d(in_channels, channels, 1, stride=2, bias=False)

    def forward(self, x):
        return torch.relu(self.body(x) + self.skip(x))


class ResidualCNNDecoder(nn.Module):
    """The seed's baseline: 4 residual layers (stride 2), global pooling, linear."""

    def __init__(self, n_bits: int, channels: int = 64):
        super().__init__()
        self.features = nn.Sequential(*[_Residual(3 if i == 0 else channels, channels) for i in range(4)])
        self.head = nn.Linear(channels, n_bits)

    def forward(self, image):
        return self.head(self.features(image).mean(dim=(2, 3)))


class UVDecoder(nn.Module):
    """Informed decoder: reads an un-rendered UV map (see reading.relight.uv_maps), not a picture.

    Input (B, 10, G, G): per UV cell, what the original texture under a fitted light leaves
    unexplained in the picture (3), the picture (3), the original albedo (3) and the coverage (1). The
    map is in absolute UV coordinates, so the head is position-aware (flatten + linear) and reads
    where each bit's pattern sits.
    """

    def __init__(self, n_bits: int, channels: int = 32, grid: int = 64):
        super().__init__()
        if grid % 8:
            raise ValueError("uv_grid must be a multiple of 8")
        self.features = nn.Sequential(ConvBNReLU(10, channels), ConvBNReLU(channels, channels, stride=2),
                                      ConvBNReLU(channels, channels, stride=2), ConvBNReLU(channels, channels, stride=2))
        self.head = nn.Linear(channels * (grid // 8) ** 2, n_bits)

    def forward(self, maps: torch.Tensor) -> torch.Tensor:
        covered = maps[:, 9:10]
        inputs = torch.cat([maps[:, :3], (2 * maps[:, 3:9] - 1) * covered, covered], dim=1)
        return self.head(self.features(inputs).flatten(1))
