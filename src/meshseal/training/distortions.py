"""Differentiable distortions: the seed's 3D ones on the mesh, and 2D attacks on rendered pictures.

Each takes a `strength` in [0, 1] that scales its range (1 = the range named in its docstring) and
a torch.Generator, so a seeded run draws the same distortions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..imaging import gaussian_blur


def _uniform(n, low, high, generator, device, dtype):
    return low + (high - low) * torch.rand(n, generator=generator).to(device=device, dtype=dtype)


# ---------------------------------------------------------------- 3D (on vertices)


def vertex_noise(positions: torch.Tensor, strength: float, generator=None) -> torch.Tensor:
    """Additive Gaussian noise on positions, sigma up to 0.01 (the seed's Table 6)."""
    noise = torch.randn(positions.shape, generator=generator).to(positions)
    return positions + 0.01 * strength * noise


def axis_angle_matrix(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues: axes (B, 3), angles (B,) -> rotation matrices (B, 3, 3)."""
    axis = F.normalize(axis, dim=-1)
    x, y, z = axis.unbind(-1)
    zero = torch.zeros_like(x)
    cross = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(-1, 3, 3)
    eye = torch.eye(3, dtype=axis.dtype, device=axis.device).expand_as(cross)
    s, c = torch.sin(angle)[:, None, None], torch.cos(angle)[:, None, None]
    return eye + s * cross + (1 - c) * cross @ cross


def random_rotation(positions, normals, strength: float, generator=None):
    """Rotation about a random axis by up to +-pi/6 (the seed's Table 6)."""
    n = positions.shape[0]
    axis = torch.randn(n, 3, generator=generator).to(positions)
    angle = _uniform(n, -math.pi / 6 * strength, math.pi / 6 * strength, generator, positions.device, positions.dtype)
    rotation = axis_angle_matrix(axis, angle)
    return positions @ rotation.transpose(1, 2), normals @ rotation.transpose(1, 2)


def random_scaling(positions, strength: float, generator=None):
    """Uniform scaling by a factor in [1 - 0.25, 1 + 0.25] (the seed: < 25 %)."""
    scale = _uniform(positions.shape[0], 1 - 0.25 * strength, 1 + 0.25 * strength, generator,
                     positions.device, positions.dtype)
    return positions * scale[:, None, None]


def random_crop_faces(positions, faces, strength: float, generator=None):
    """Remove the faces beyond a random plane, up to 20 % of them (the seed: cropping < 20 %).

    Removed faces become degenerate [0, 0, 0] so the batch keeps its shape.
    """
    n, n_faces = faces.shape[0], faces.shape[-2]
    faces = faces.expand(n, -1, -1) if faces.dim() == 3 else faces.unsqueeze(0).expand(n, -1, -1)
    direction = F.normalize(torch.randn(n, 3, generator=generator), dim=-1).to(positions)
    fraction = 0.2 * strength * torch.rand(n, generator=generator).to(positions)
    centroids = positions.detach().gather(1, faces.reshape(n, -1, 1).expand(-1, -1, 3)).reshape(n, n_faces, 3, 3).mean(2)
    height = (centroids * direction[:, None]).sum(-1)  # (B, F)
    rank = ((1.0 - fraction) * (n_faces - 1)).long().clamp(0, n_faces - 1)
    threshold = height.sort(dim=1).values.gather(1, rank.unsqueeze(1))  # per-mesh quantile
    keep = height <= threshold
    return torch.where(keep.unsqueeze(-1), faces, torch.zeros_like(faces))


@dataclass
class Distortions3D:
    """The seed's 3D distortion layer; probabilities of applying each, and their strength."""

    strength: float = 1.0
    p_noise: float = 0.25
    p_rotation: float = 0.25
    p_scaling: float = 0.25
    p_crop: float = 0.25

    def __call__(self, positions, normals, faces, generator=None):
        if self.strength <= 0:
            return positions, normals, faces
        draw = torch.rand(4, generator=generator)
        if draw[0] < self.p_noise:
            positions = vertex_noise(positions, self.strength, generator)
        if draw[1] < self.p_rotation:
            positions, normals = random_rotation(positions, normals, self.strength, generator)
        if draw[2] < self.p_scaling:
            positions = random_scaling(positions, self.strength, generator)
        if draw[3] < self.p_crop:
            faces = random_crop_faces(positions, faces, self.strength, generator)
        return positions, normals, faces


# ---------------------------------------------------------------- 2D (on images (B, 3, H, W) in [0, 1])


def _dct_matrix(n: int = 8, dtype=torch.float32, device=None) -> torch.Tensor:
    k = torch.arange(n, dtype=torch.float64)
    matrix = torch.cos(math.pi * (2 * k[None, :] + 1) * k[:, None] / (2 * n)) * math.sqrt(2.0 / n)
    matrix[0] /= math.sqrt(2.0)
    return matrix.to(dtype=dtype, device=device)


_LUMA = torch.tensor([
    [16, 11, 10, 16, 24, 40, 51, 61], [12, 12, 14, 19, 26, 58, 60, 55], [14, 13, 16, 24, 40, 57, 69, 56],
    [14, 17, 22, 29, 51, 87, 80, 62], [18, 22, 37, 56, 68, 109, 103, 77], [24, 35, 55, 64, 81, 104, 113, 92],
    [49, 64, 78, 87, 103, 121, 120, 101], [72, 92, 95, 98, 112, 100, 103, 99]], dtype=torch.float32)
_CHROMA = torch.full((8, 8), 99.0)
_CHROMA[:4, :4] = torch.tensor([[17, 18, 24, 47], [18, 21, 26, 66], [24, 26, 56, 99], [47, 66, 99, 99]])


def jpeg(image: torch.Tensor, quality: float) -> torch.Tensor:
    """Differentiable JPEG: YCbCr, 8x8 DCT, quantisation with the standard tables at `quality`, rounding
    with a straight-through gradient, and back. No chroma subsampling."""
    n, _, height, width = image.shape
    pad_h, pad_w = (-height) % 8, (-width) % 8
    x = F.pad(image, (0, pad_w, 0, pad_h), mode="replicate") * 255.0
    r, g, b = x.unbind(1)
    ycc = torch.stack([0.299 * r + 0.587 * g + 0.114 * b - 128,
                       -0.168736 * r - 0.331264 * g + 0.5 * b,
                       0.5 * r - 0.418688 * g - 0.081312 * b], dim=1)
    scale = 5000.0 / quality if quality < 50 else 200.0 - 2.0 * quality
    tables = torch.stack([_LUMA, _CHROMA, _CHROMA]).to(image)
    tables = ((tables * scale + 50.0) / 100.0).floor().clamp(min=1.0)
    dct = _dct_matrix(8, image.dtype, image.device)
    hb, wb = x.shape[-2] // 8, x.shape[-1] // 8
    blocks = ycc.reshape(n, 3, hb, 8, wb, 8).permute(0, 1, 2, 4, 3, 5)  # (n, 3, hb, wb, 8, 8)
    coefficients = dct @ blocks @ dct.T
    scaled = coefficients / tables[None, :, None, None]
    rounded = scaled + (torch.round(scaled) - scaled).detach()
    blocks = dct.T @ (rounded * tables[None, :, None, None]) @ dct
    ycc = blocks.permute(0, 1, 2, 4, 3, 5).reshape(n, 3, hb * 8, wb * 8)
    y, cb, cr = ycc[:, 0] + 128, ycc[:, 1], ycc[:, 2]
    rgb = torch.stack([y + 1.402 * cr, y - 0.344136 * cb - 0.714136 * cr, y + 1.772 * cb], dim=1) / 255.0
    return rgb[..., :height, :width].clamp(0.0, 1.0)


def resize_round_trip(image: torch.Tensor, factor: float) -> torch.Tensor:
    """Downscale by `factor` and back (what re-uploads and thumbnails do)."""
    height, width = image.shape[-2:]
    small = F.interpolate(image, size=(max(8, round(height * factor)), max(8, round(width * factor))),
                          mode="bilinear", align_corners=False, antialias=True)
    return F.interpolate(small, size=(height, width), mode="bilinear", align_corners=False)


def crop_region(image: torch.Tensor, keep: float, generator=None, fill: float = 0.0) -> torch.Tensor:
    """Keep a random axis-aligned window with `keep` of each side; fill the rest (a cropped picture)."""
    height, width = image.shape[-2:]
    h, w = max(1, round(height * keep)), max(1, round(width * keep))
    top = int(torch.randint(0, height - h + 1, (1,), generator=generator))
    left = int(torch.randint(0, width - w + 1, (1,), generator=generator))
    mask = torch.zeros_like(image[:, :1])
    mask[..., top:top + h, left:left + w] = 1.0
    return image * mask + fill * (1 - mask)


@dataclass
class Distortions2D:
    """One random 2D attack per batch (or none), HiDDeN-style combined training.

    At strength 1: JPEG quality 50-95, resize factor 0.5-1, crop keeping 70-100 % per side, blur
    sigma 0-1 px, brightness +-0.2 and contrast 0.8-1.2, Gaussian noise sigma 0-0.03.
    """

    strength: float = 1.0
    attacks: tuple = ("identity", "jpeg", "resize", "crop", "blur", "color", "noise")

    def __call__(self, image: torch.Tensor, generator=None) -> torch.Tensor:
        if self.strength <= 0:
            return image
        name = self.attacks[int(torch.randint(len(self.attacks), (1,), generator=generator))]
        return self.apply(name, image, generator)

    def apply(self, name: str, image: torch.Tensor, generator=None) -> torch.Tensor:
        s, u = self.strength, float(torch.rand(1, generator=generator))
        if name == "jpeg":
            return jpeg(image, 95.0 - 45.0 * s * u)
        if name == "resize":
            return resize_round_trip(image, 1.0 - 0.5 * s * u)
        if name == "crop":
            return crop_region(image, 1.0 - 0.3 * s * u, generator)
        if name == "blur":
            return gaussian_blur(image, 1.0 * s * u)
        if name == "color":
            n = image.shape[0]
            brightness = (0.4 * torch.rand(n, 1, 1, 1, generator=generator) - 0.2).to(image) * s
            contrast = (1.0 + (0.4 * torch.rand(n, 1, 1, 1, generator=generator) - 0.2) * s).to(image)
            mean = image.mean(dim=(1, 2, 3), keepdim=True)
            return ((image - mean) * contrast + mean + brightness).clamp(0.0, 1.0)
        if name == "noise":
            noise = torch.randn(image.shape, generator=generator).to(image)
            return (image + 0.03 * s * u * noise).clamp(0.0, 1.0)
        return image
