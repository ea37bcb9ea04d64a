"""Texture encoders: texture + message -> bounded residual on the texture.

Both work at a fixed working resolution: a texture of any size and aspect is resized to `size`, the
residual is computed there and upsampled (bilinear) onto the full-resolution texture, as image
watermarkers do. The residual is bounded by `strength * tanh(.)` or, with `rms` > 0, rescaled to that
RMS: a fixed-power mark, whose pattern alone is learned.
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
    rms: float = 0.0  # > 0: the residual is rescaled to this RMS (a fixed-power mark; strength is unused)
    rms_after_clip: bool = False  # hold the RMS of what survives clipping to [0, 1], not of the raw residual

    def residual(self, texture: torch.Tensor, message: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def forward(self, texture: torch.Tensor, message: torch.Tensor) -> torch.Tensor:
        """texture (B, 3, H, W) in [0, 1], message (B, N) -> watermarked texture (B, 3, H, W) in [0, 1]."""
        height, width = texture.shape[-2:]
        working = texture
        if (height, width) != (self.size, self.size):
            working = F.interpolate(texture, size=(self.size, self.size), mode="bilinear", align_corners=False,
                                    antialias=True)
        raw = self.residual(working, message)
        if self.rms > 0:  # always the full budget: the decoder has a mark to find from the first step
            residual = self.rms * raw / raw.pow(2).mean(dim=(1, 2, 3), keepdim=True).sqrt().clamp_min(1e-8)
            for _ in range(2 if self.rms_after_clip else 0):  # else an encoder can hide its power in clipped texels
                kept = (working + residual).clamp(0.0, 1.0) - working
                residual = self.rms * kept / kept.pow(2).mean(dim=(1, 2, 3), keepdim=True).sqrt().clamp_min(1e-8)
        else:
            residual = self.strength * torch.tanh(raw)
        if (height, width) != (self.size, self.size):
            residual = F.interpolate(residual, size=(height, width), mode="bilinear", align_corners=False)
        return (texture + residual).clamp(0.0, 1.0)


class HiddenTextureEncoder(TextureEncoder):
    """HiDDeN's encoder: conv-BN-ReLU blocks, the message broadcast and concatenated, two more blocks.

    `downsample` > 1 runs every block at 1/downsample of the working size and upsamples the residual:
    a CPU-sized variant whose marks are smoother, so they survive the resampling of rendering.
    `tile` > 0 adds a learned *periodic carrier*: a linear map from the bits to a tile x tile pattern
    repeated over the texture. A constant broadcast of the bits gives convolutions nothing spatial to
    build on (HiDDeN must borrow structure from the image, which trains slowly); the carrier gives every
    bit a spatial signature from the start, and its periodicity puts the whole message in every patch
    of the surface, whatever part of it a view shows. `keying` 'fsk' gives each value of a bit its own
    carrier (the map reads the bits and their complements), so a reader can tell a bit by which pattern
    is there, whatever its phase, instead of by its sign. `coords` adds the texel's (u, v) as inputs: the
    encoder can then give each bit a place on the surface, for views whose range keeps places in place.
    """

    def __init__(self, n_bits: int, channels: int = 64, blocks: int = 4, size: int = 128,
                 strength: float = 0.1, downsample: int = 1, tile: int = 0, tile_channels: int = 8,
                 keying: str = "antipodal", coords: bool = False):
        super().__init__()
        if keying not in ("antipodal", "fsk"):
            raise ValueError(f"texture_tile_keying must be antipodal or fsk, not '{keying}'")
        self.size, self.strength, self.downsample, self.tile = size, strength, downsample, tile
        self.keying, self.coords = keying, coords
        layers = [ConvBNReLU(3, channels)] + [ConvBNReLU(channels, channels) for _ in range(blocks - 1)]
        self.features = nn.Sequential(*layers)
        carrier_channels = tile_channels if tile else 0
        keys = 2 * n_bits if keying == "fsk" else n_bits
        self.carrier = nn.Linear(keys, tile_channels * tile * tile) if tile else None
        self.carrier_channels = carrier_channels
        self.after = ConvBNReLU(channels + 3 + n_bits + carrier_channels + (2 if coords else 0), channels)
        self.out = nn.Conv2d(channels, 3, 1)

    def residual(self, texture, message):
        full_size = texture.shape[-2:]
        if self.downsample > 1:
            texture = F.interpolate(texture, scale_factor=1.0 / self.downsample, mode="bilinear",
                                    align_corners=False, antialias=True)
        height, width = texture.shape[-2:]
        inputs = [self.features(texture), texture, broadcast_message(message, height, width)]
        if self.coords:
            v, u = torch.meshgrid(torch.linspace(-1.0, 1.0, height, device=texture.device, dtype=texture.dtype),
                                  torch.linspace(-1.0, 1.0, width, device=texture.device, dtype=texture.dtype),
                                  indexing="ij")
            inputs.append(torch.stack([u, v])[None].expand(texture.shape[0], -1, -1, -1))
        if self.carrier is not None:
            keys = torch.cat([message, 1.0 - message], dim=1) if self.keying == "fsk" else 2.0 * message - 1.0
            pattern = self.carrier(keys).reshape(-1, self.carrier_channels, self.tile, self.tile)
            repeats = (-(-height // self.tile), -(-width // self.tile))
            inputs.append(pattern.repeat(1, 1, *repeats)[..., :height, :width])
        residual = self.out(self.after(torch.cat(inputs, dim=1)))
        if self.downsample > 1:
            residual = F.interpolate(residual, size=full_size, mode="bilinear", align_corners=False)
        return residual


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
