"""Splatting (Cole, Genova et al., "Differentiable Surface Rendering via Non-Differentiable Sampling").

Each foreground pixel's shaded colour is spread over its 3x3 neighbourhood with Gaussian weights
centred on its *splat position*: the surface point's screen position, whose value is the pixel centre
but whose gradient follows the vertices. This turns hard silhouettes into smooth functions of the
vertex positions and antialiases edges; interior pixels keep a total weight of exactly one.

Because every splat position equals its pixel centre in the forward pass, the Gaussian weights are
linearised around the centre: w_o(d) = g_o (1 + o.d / sigma^2) for a splat displaced by d. Value and
first derivative are exact at d = 0, and the whole splat becomes one 3x3 convolution (fast on CPU).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def _kernels(sigma: float, dtype, device) -> torch.Tensor:
    """(3, 3, 3): the normalised Gaussian g and its x- and y-moment kernels g*ox/sigma^2, g*oy/sigma^2,
    as correlation kernels (flipped offsets), indexed [kind, row, col]."""
    offsets = torch.tensor([-1.0, 0.0, 1.0], dtype=torch.float64)
    oy, ox = torch.meshgrid(offsets, offsets, indexing="ij")
    gauss = torch.exp(-(ox ** 2 + oy ** 2) / (2.0 * sigma * sigma))
    gauss = gauss / gauss.sum()
    # Scatter to offset o equals correlation at -o: flip the moment kernels' sign.
    return torch.stack([gauss, -gauss * ox / sigma ** 2, -gauss * oy / sigma ** 2]).to(dtype=dtype, device=device)


def splat(color: torch.Tensor, alpha: torch.Tensor, splat_xy: torch.Tensor, background: torch.Tensor,
          sigma: float = 0.5) -> tuple[torch.Tensor, torch.Tensor]:
    """Splat colours (B, H, W, C) with coverage alpha (B, H, W) at positions (B, H, W, 2) in pixels.

    splat_xy must lie at (or within a small fraction of a pixel of) the pixel centres (j + 0.5, i + 0.5).
    Returns the composited image (B, H, W, C) over `background` (C,) or (B, C) and the coverage (B, H, W).
    """
    n_batch, height, width, channels = color.shape
    rows = torch.arange(height, dtype=color.dtype, device=color.device).reshape(1, height, 1) + 0.5
    cols = torch.arange(width, dtype=color.dtype, device=color.device).reshape(1, 1, width) + 0.5
    dx = (splat_xy[..., 0] - cols).unsqueeze(1)  # (B, 1, H, W) displacement from the pixel centre
    dy = (splat_xy[..., 1] - rows).unsqueeze(1)
    values = torch.cat([color.permute(0, 3, 1, 2) * alpha.unsqueeze(1), alpha.unsqueeze(1)], dim=1)
    stacked = torch.cat([values, values * dx, values * dy], dim=1)  # (B, 3(C+1), H, W)
    kernels = _kernels(sigma, color.dtype, color.device)
    n = channels + 1
    weight = color.new_zeros(n, 3 * n, 3, 3)
    index = torch.arange(n, device=color.device)
    for kind in range(3):
        weight[index, kind * n + index] = kernels[kind]
    accumulated = F.conv2d(stacked, weight, padding=1)  # (B, C+1, H, W)
    coverage = accumulated[:, -1]
    image = accumulated[:, :-1] / coverage.clamp_min(1.0).unsqueeze(1)
    image = image + (1.0 - coverage.clamp(max=1.0)).unsqueeze(1) * background.to(color.dtype).reshape(-1, channels, 1, 1)
    return image.permute(0, 2, 3, 1), coverage.clamp(max=1.0)
