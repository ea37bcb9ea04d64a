"""Texture encoders: texture + message -> bounded residual on the texture.

Both work at a fixed working resolution: a texture of any size and aspect is resized to `size`, the
residual is computed there and upsampled (bilinear) onto the full-resolution texture, as image
watermarkers do. The residual is bounded by `strength * tanh(.)`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .blocks import ConvBNReLU


def broadcast_message(message: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(B, N) bits in {0, 1} -> (B, N, H, W) in {-1, 1}, each bit replicated over the image."""
    return (2.0 * message - 1.0)[:, :, None, None].expand(-1, -1, height, width)


class TextureEncoder(nn.Module):
    """Residual at the working size, applied at any size."""

    size: int = 128
    strength: float = 0.1

    def residual(self, texture: torch.Tensor, message: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def forward(self, texture: torch.Tensor, message: torch.Tensor) -> torch.Tensor:
        """texture (B, 3, H, W) in [0, 1], message (B, N) -> watermarked texture (B, 3, H, W) in [0, 1]."""
        height, width = texture.shape[-2:]
        working = texture
        if (height, width) != (self.size, self.size):
            working = F.interpolate(texture, size=(self.size, self.size), mode="bilinear", align_corners=False,
                                    antialias=True)
        residual = self.strength * torch.tanh(self.residual(working, message))
        if (height, width) != (self.size, self.size):
            residual = F.interpolate(residual, size=(height, width), mode="bilinear", align_corners=False)
        return (texture + residual).clamp(0.0, 1.0)


class HiddenTextureEncoder(TextureEncoder):
    """HiDDeN's encoder: conv-BN-ReLU blocks, the message broadcast and concatenated, two more blocks.

    `downsample` > 1 runs the blocks at 1/downsample resolution (a CPU-sized variant) and upsamples.
    """

    def __init__(self, n_bits: int, channels: int = 64, blocks: int = 4, size: int = 128,
                 strength: float = 0.1, downsample: int = 1):
        super().__init__()
        self.size, self.strength, self.downsample = size, strength, downsample
        layers = [ConvBNReLU(3, channels, stride=downsample)]
        layers += [ConvBNReLU(channels, channels) for _ in range(blocks - 1)]
        self.features = nn.Sequential(*layers)
        self.after = ConvBNReLU(channels + 3 + n_bits, channels)
        self.out = nn.Conv2d(channels, 3, 1)

    def residual(self, texture, message):
        features = self.features(texture)
        if self.downsample > 1:
            features = F.interpolate(features, size=texture.shape[-2:], mode="bilinear", align_corners=False)
        bits = broadcast_message(message, *texture.shape[-2:])
        return self.out(self.after(torch.cat([features, texture, bits], dim=1)))


class UNetTextureEncoder(TextureEncoder):
    """A fully convolutional U-Net (64-128-256-512 with max pooling) with the message at the bottleneck
    and at the input."""

    def __init__(self, n_bits: int, widths=(64, 128, 256, 512), size: int = 128, strength: float = 0.1):
        super().__init__()
        self.size, self.strength = size, strength
        self.down = nn.ModuleList()
        in_channels = 3 + n_bits
        for width in widths:
            self.down.append(nn.Sequential(ConvBNReLU(in_channels, width), ConvBNReLU(width, width)))
            in_channels = width
        self.bottleneck = ConvBNReLU(widths[-1] + n_bits, widths[-1])
        self.up = nn.ModuleList()
        for skip, width in zip(reversed(widths[:-1]), reversed(widths[1:])):
            self.up.append(nn.Sequential(ConvBNReLU(width + skip, skip), ConvBNReLU(skip, skip)))
        self.out = nn.Conv2d(widths[0], 3, 1)

    def residual(self, texture, message):
        x = torch.cat([texture, broadcast_message(message, *texture.shape[-2:])], dim=1)
        skips = []
        for index, block in enumerate(self.down):
            if index:
                x = F.max_pool2d(x, 2)
            x = block(x)
            skips.append(x)
        x = self.bottleneck(torch.cat([x, broadcast_message(message, *x.shape[-2:])], dim=1))
        for block, skip in zip(self.up, reversed(skips[:-1])):
            x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = block(torch.cat([x, skip], dim=1))
        return self.out(x)
