"""Bilinear texture lookup with REPEAT wrapping and no mipmaps (as the OpenGL reference)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def sample_texture(texture: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Sample one texture (C, H, W) at uv (P, 2) -> (P, C); uv (0, 0) is the image's bottom-left.

    Wrapping is exact REPEAT: the texture is padded by one texel circularly and u, v are taken
    modulo 1, so bilinear weights across the seam match OpenGL's GL_REPEAT + GL_LINEAR.
    """
    channels, height, width = texture.shape
    padded = F.pad(texture.unsqueeze(0), (1, 1, 1, 1), mode="circular")
    u = uv[:, 0] - torch.floor(uv[:, 0].detach())
    v = uv[:, 1] - torch.floor(uv[:, 1].detach())
    # Texel coordinates in the padded image (texel centres at k + 0.5), then grid_sample's [-1, 1].
    x = (u * width + 1.0) / (width + 2) * 2.0 - 1.0
    y = ((1.0 - v) * height + 1.0) / (height + 2) * 2.0 - 1.0
    grid = torch.stack([x, y], dim=-1).reshape(1, 1, -1, 2).to(texture.dtype)
    sampled = F.grid_sample(padded, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return sampled.reshape(channels, -1).transpose(0, 1)


def sample_textures(textures, uv: torch.Tensor, texture_index: torch.Tensor) -> torch.Tensor:
    """Sample from a list (or (N, C, H, W) stack) of textures, each fragment from `texture_index` (P,).

    A texture entry of None is plain white.
    """
    out = uv.new_ones(uv.shape[0], 3)
    if uv.shape[0] == 0:
        return out
    for index in torch.unique(texture_index).tolist():
        texture = textures[index]
        if texture is None:
            continue
        mask = texture_index == index
        selected = torch.nonzero(mask).squeeze(1)
        out = out.index_copy(0, selected, sample_texture(texture, uv[selected]).to(out.dtype))
    return out
