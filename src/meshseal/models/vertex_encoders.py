"""Vertex encoders: per-vertex (normal, uv) + message -> bounded residuals on normals and uvs.

Positions are an input (they say where a vertex is) but are never changed: moving vertices makes
degenerate triangles (the seed, 3.2). PointNet pools a global feature with max; PointNet v2 is fully
convolutional with global average pooling (any vertex count; padded vertices are masked out).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def _mlp(sizes: list[int]) -> nn.Sequential:
    layers = []
    for a, b in zip(sizes[:-1], sizes[1:]):
        layers += [nn.Conv1d(a, b, 1), nn.BatchNorm1d(b), nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


class PointNetVertexEncoder(nn.Module):
    def __init__(self, n_bits: int, pooling: str = "avg", width: int = 64, normal_strength: float = 0.05,
                 uv_strength: float = 0.002):
        super().__init__()
        if pooling not in ("max", "avg"):
            raise ValueError("pooling must be 'max' (PointNet) or 'avg' (PointNet v2)")
        self.pooling, self.normal_strength, self.uv_strength = pooling, normal_strength, uv_strength
        in_channels = 3 + 3 + 2 + n_bits  # position, normal, uv, message
        self.local = _mlp([in_channels, width, width])
        self.global_features = _mlp([width, 2 * width, 4 * width])
        self.head = nn.Sequential(_mlp([width + 4 * width + n_bits, 2 * width, width]), nn.Conv1d(width, 5, 1))

    def forward(self, positions, normals, uvs, message, vertex_mask=None):
        """(B, V, 3), (B, V, 3), (B, V, 2), (B, N), mask (B, V) -> watermarked normals, uvs."""
        n_vertices = positions.shape[1]
        bits = (2.0 * message - 1.0).unsqueeze(-1).expand(-1, -1, n_vertices)
        x = torch.cat([positions.transpose(1, 2), normals.transpose(1, 2), uvs.transpose(1, 2), bits], dim=1)
        local = self.local(x)
        features = self.global_features(local)
        mask = torch.ones_like(features[:, :1]) if vertex_mask is None else vertex_mask.unsqueeze(1).to(features.dtype)
        if self.pooling == "max":
            pooled = features.masked_fill(mask == 0, float("-inf")).amax(dim=-1, keepdim=True)
        else:
            pooled = (features * mask).sum(-1, keepdim=True) / mask.sum(-1, keepdim=True).clamp_min(1.0)
        out = self.head(torch.cat([local, pooled.expand(-1, -1, n_vertices), bits], dim=1)).transpose(1, 2)
        new_normals = F.normalize(normals + self.normal_strength * torch.tanh(out[..., :3]), dim=-1)
        new_uvs = uvs + self.uv_strength * torch.tanh(out[..., 3:])
        if vertex_mask is not None:
            keep = vertex_mask.unsqueeze(-1) > 0
            new_normals, new_uvs = torch.where(keep, new_normals, normals), torch.where(keep, new_uvs, uvs)
        return new_normals, new_uvs
