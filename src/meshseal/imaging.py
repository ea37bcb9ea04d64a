"""Image helpers shared by reading and training: a separable Gaussian blur on (B, C, H, W) tensors and
the sRGB transfer curve."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def blur_radius(sigma: float) -> int:
    """How many pixels `gaussian_blur` reaches on each side."""
    return max(1, int(math.ceil(2.5 * sigma)))


def gaussian_blur(image: torch.Tensor, sigma: float) -> torch.Tensor:
    if sigma <= 0:
        return image
    radius = blur_radius(sigma)
    x = torch.arange(-radius, radius + 1, dtype=image.dtype, device=image.device)
    kernel = torch.exp(-x * x / (2 * sigma * sigma))
    kernel = kernel / kernel.sum()
    channels = image.shape[1]
    padded = F.pad(image, (radius, radius, radius, radius), mode="replicate")
    out = F.conv2d(padded, kernel.reshape(1, 1, 1, -1).expand(channels, 1, 1, -1), groups=channels)
    return F.conv2d(out, kernel.reshape(1, 1, -1, 1).expand(channels, 1, -1, 1), groups=channels)


def srgb_to_linear(values: torch.Tensor) -> torch.Tensor:
    """sRGB-encoded values -> linear light (IEC 61966-2-1; values outside [0, 1], a prediction's
    overshoot, continue the curve's two pieces)."""
    return torch.where(values <= 0.04045, values / 12.92, ((values.clamp_min(0.0) + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(values: torch.Tensor) -> torch.Tensor:
    """Linear light in [0, 1] -> sRGB-encoded values (IEC 61966-2-1)."""
    values = values.clamp(0.0, 1.0)
    return torch.where(values <= 0.0031308, 12.92 * values, 1.055 * values.clamp_min(1e-12) ** (1 / 2.4) - 0.055)
