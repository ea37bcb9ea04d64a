"""Image filters shared by reading and training: a separable Gaussian blur on (B, C, H, W) tensors."""

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
