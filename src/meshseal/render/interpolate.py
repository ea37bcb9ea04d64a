"""Interpolation of per-vertex attributes at fragments, and fragments back to images."""

from __future__ import annotations

import torch

from .rasterizer import Fragments, gather_corners


def interpolate(attributes: torch.Tensor, fragments: Fragments, perspective: bool = True) -> torch.Tensor:
    """Interpolate per-vertex attributes (B, V, C) at the fragments -> (P, C)."""
    values = gather_corners(attributes, fragments.batch, fragments.vertex)  # (P, 3, C)
    weights = fragments.bary if perspective else fragments.screen_bary
    # Two fused multiply-adds: on the CPU cheaper than a broadcast product and a sum over corners (no (P, 3, C) temporary).
    first = values[:, 0] * weights[:, 0:1]
    return torch.addcmul(torch.addcmul(first, values[:, 1], weights[:, 1:2]), values[:, 2], weights[:, 2:3])


def scatter_to_image(values: torch.Tensor, fragments: Fragments, fill=0.0) -> torch.Tensor:
    """Foreground values (P, C) -> image (B, H, W, C) with `fill` on the background."""
    n_batch, height, width = fragments.shape
    channels = values.shape[-1]
    if torch.is_tensor(fill):
        image = fill.to(values.dtype).expand(n_batch * height * width, channels).clone()
    else:
        image = values.new_full((n_batch * height * width, channels), float(fill))
    image = image.index_copy(0, fragments.pixel, values)
    return image.reshape(n_batch, height, width, channels)
