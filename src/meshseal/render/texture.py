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
    if torch.is_tensor(textures):
        return _sample_stack(textures, uv, texture_index).to(out.dtype)
    if len(textures) == 1 and textures[0] is not None and bool((texture_index == 0).all()):
        return sample_texture(textures[0], uv).to(out.dtype).contiguous()  # what the loop gives, in its layout
    for index in torch.unique(texture_index).tolist():
        texture = textures[index]
        if texture is None:
            continue
        mask = texture_index == index
        selected = torch.nonzero(mask).squeeze(1)
        out = out.index_copy(0, selected, sample_texture(texture, uv[selected]).to(out.dtype))
    return out


def _sample_stack(textures: torch.Tensor, uv: torch.Tensor, texture_index: torch.Tensor) -> torch.Tensor:
    """`sample_texture` for a stack (N, C, H, W), every fragment from its own texture in one gather: no
    per-texture loop, so no host round trip per texture on a GPU (a training batch has 2 x 32 of them)."""
    n_textures, channels, height, width = textures.shape
    # Texel-major rows (contiguous: the permuted pad's reshape is a view with channel-major strides, on
    # which a row gather is over ten times slower on a CPU).
    padded = F.pad(textures, (1, 1, 1, 1), mode="circular").permute(0, 2, 3, 1).reshape(-1, channels).contiguous()
    u = uv[:, 0] - torch.floor(uv[:, 0].detach())
    v = uv[:, 1] - torch.floor(uv[:, 1].detach())
    # Positions in the padded texture's texel grid (centres at integers): within [0.5, size + 0.5].
    x = (u * width + 0.5).to(textures.dtype)
    y = ((1.0 - v) * height + 0.5).to(textures.dtype)
    x0, y0 = torch.floor(x.detach()), torch.floor(y.detach())
    wx, wy = (x - x0).unsqueeze(1), (y - y0).unsqueeze(1)
    col = x0.long().clamp(0, width)
    row = y0.long().clamp(0, height)
    base = texture_index.long() * ((height + 2) * (width + 2)) + row * (width + 2) + col
    top = torch.lerp(padded.index_select(0, base), padded.index_select(0, base + 1), wx)
    bottom = torch.lerp(padded.index_select(0, base + width + 2), padded.index_select(0, base + width + 3), wx)
    return torch.lerp(top, bottom, wy)
