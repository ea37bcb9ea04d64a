"""`imaging.gaussian_blur` in one compiled pass on the CPU, for reading's many small blurs.

torch runs the blur as two grouped convolutions; on one CPU thread a grouped convolution of a few
dozen small planes (`models.spread.local_mean` blurs one plane per channel plus the coverage) costs
many times its arithmetic. `gaussian_blur` here does the same arithmetic in the same order: the
kernel built as `imaging.gaussian_blur` builds it, edges replicated, each output the fused
multiply-add sum over the taps from the first, the rows first and then the columns; it gives the same
bits as torch's convolution on the CPUs it was compared on (tests/test_render.py). Where it does not
apply (gradients, another device or dtype, a single plane, which torch convolves another way) it is
`imaging.gaussian_blur` itself.
"""

from __future__ import annotations

import numpy as np
import torch

from ..imaging import blur_radius
from ..imaging import gaussian_blur as torch_blur
from . import compiled
from .compiled import njit


@njit(fastmath={"contract"}, cache=True)
def _separable(planes, kernel, radius):  # pragma: no cover - compiled
    count, height, width = planes.shape
    taps = kernel.shape[0]
    out = np.empty((count, height, width), np.float32)
    row = np.empty(width + 2 * radius, np.float32)
    middle = np.empty((height + 2 * radius, width), np.float32)
    zero = np.float32(0.0)
    for plane in range(count):
        for i in range(height):  # along the rows, the row's ends replicated
            for j in range(width + 2 * radius):
                row[j] = planes[plane, i, min(max(j - radius, 0), width - 1)]
            total = middle[i + radius]
            for j in range(width):
                total[j] = zero
            for t in range(taps):
                weight = kernel[t]
                for j in range(width):
                    total[j] += weight * row[j + t]
        for i in range(radius):  # the first and last rows replicated
            middle[i] = middle[radius]
            middle[height + radius + i] = middle[height + radius - 1]
        for i in range(height):  # along the columns
            total = out[plane, i]
            for j in range(width):
                total[j] = zero
            for t in range(taps):
                weight = kernel[t]
                source = middle[i + t]
                for j in range(width):
                    total[j] += weight * source[j]
    return out


def gaussian_blur(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """`imaging.gaussian_blur` of `image` (B, C, H, W), compiled where it applies (see the module)."""
    if (sigma <= 0 or image.device.type != "cpu" or image.dtype != torch.float32 or image.dim() != 4
            or image.shape[1] < 2 or image.numel() == 0 or (image.requires_grad and torch.is_grad_enabled())):
        return torch_blur(image, sigma)
    if compiled.spare(image.numel()):  # a small job while the kernels are not loaded: torch's own, the same bits
        with compiled.in_torch():
            return torch_blur(image, sigma)
    radius = blur_radius(sigma)
    x = torch.arange(-radius, radius + 1, dtype=image.dtype)
    kernel = torch.exp(-x * x / (2 * sigma * sigma))
    kernel = kernel / kernel.sum()
    batch, channels, height, width = image.shape
    planes = np.ascontiguousarray(image.detach().reshape(batch * channels, height, width).numpy())
    return torch.from_numpy(_separable(planes, kernel.numpy(), radius)).reshape(batch, channels, height, width)
