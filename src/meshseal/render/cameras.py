"""Cameras in the OpenGL convention (see docs/conventions.md) and the seed's view samplers."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch


@dataclass
class Cameras:
    """A batch of pinhole cameras: eye, look-at point and up vector, each (B, 3).

    `principal` shifts the image centre by (x, y) in normalised device coordinates: the camera of a
    crop of a picture, which registration (see `register`) uses.
    """

    eye: torch.Tensor
    at: torch.Tensor
    up: torch.Tensor
    fov_y: float = 60.0
    near: float = 0.1
    far: float = 100.0
    principal: tuple[float, float] = (0.0, 0.0)

    def __len__(self) -> int:
        return self.eye.shape[0]

    def to(self, device=None, dtype=None) -> "Cameras":
        return replace(self, eye=self.eye.to(device, dtype), at=self.at.to(device, dtype), up=self.up.to(device, dtype))

    def __getitem__(self, index) -> "Cameras":
        index = [index] if isinstance(index, int) else index
        return replace(self, eye=self.eye[index], at=self.at[index], up=self.up[index])

    def view_matrix(self) -> torch.Tensor:
        """World -> view (B, 4, 4); the camera looks down its -Z axis."""
        return look_at(self.eye, self.at, self.up)

    def projection_matrix(self, aspect: float) -> torch.Tensor:
        """View -> clip (4, 4), gluPerspective (with the principal point shift)."""
        matrix = perspective(self.fov_y, aspect, self.near, self.far, self.eye.dtype, self.eye.device)
        matrix[0, 2], matrix[1, 2] = -self.principal[0], -self.principal[1]
        return matrix

    def world_to_clip(self, points: torch.Tensor, aspect: float) -> torch.Tensor:
        """(B, N, 3) world points -> (B, N, 4) clip coordinates."""
        matrix = self.projection_matrix(aspect) @ self.view_matrix()
        homogeneous = torch.cat([points, torch.ones_like(points[..., :1])], dim=-1)
        return homogeneous @ matrix.transpose(1, 2)


def look_at(eye: torch.Tensor, at: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    forward = torch.nn.functional.normalize(at - eye, dim=-1)
    right = torch.nn.functional.normalize(torch.cross(forward, up, dim=-1), dim=-1)
    true_up = torch.cross(right, forward, dim=-1)
    rotation = torch.stack([right, true_up, -forward], dim=1)  # rows
    matrix = torch.zeros(eye.shape[0], 4, 4, dtype=eye.dtype, device=eye.device)
    matrix[:, :3, :3] = rotation
    matrix[:, :3, 3] = -(rotation @ eye.unsqueeze(-1)).squeeze(-1)
    matrix[:, 3, 3] = 1.0
    return matrix


def perspective(fov_y: float, aspect: float, near: float, far: float, dtype=torch.float32, device=None) -> torch.Tensor:
    f = 1.0 / math.tan(math.radians(fov_y) / 2.0)
    matrix = torch.zeros(4, 4, dtype=dtype, device=device)
    matrix[0, 0] = f / aspect
    matrix[1, 1] = f
    matrix[2, 2] = (far + near) / (near - far)
    matrix[2, 3] = 2.0 * far * near / (near - far)
    matrix[3, 2] = -1.0
    return matrix


def fibonacci_directions(n: int) -> torch.Tensor:
    """n nearly uniform unit vectors on the sphere (n, 3)."""
    index = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * index / n
    radius = torch.sqrt(1.0 - z * z)
    angle = math.pi * (3.0 - math.sqrt(5.0)) * index
    return torch.stack([radius * torch.cos(angle), radius * torch.sin(angle), z], dim=-1).float()


def _batch(vector, n: int, dtype=torch.float32, device=None) -> torch.Tensor:
    return torch.as_tensor(vector, dtype=dtype, device=device).reshape(1, 3).expand(n, 3).clone()


def cameras_from_eyes(eye: torch.Tensor, fov_y: float = 60.0) -> Cameras:
    """Cameras at `eye` (B, 3) looking at the origin with +Z up (the canonical frame)."""
    n = eye.shape[0]
    return Cameras(eye, torch.zeros_like(eye), _batch((0.0, 0.0, 1.0), n, eye.dtype, eye.device), fov_y)


def sample_seed_cameras(n: int, generator: torch.Generator | None = None) -> Cameras:
    """The seed's training range: x = 0, y ~ U[-3, -2], z ~ U[2, 4], looking at the origin, fov_y 60."""
    y = -3.0 + torch.rand(n, generator=generator)
    z = 2.0 + 2.0 * torch.rand(n, generator=generator)
    return cameras_from_eyes(torch.stack([torch.zeros(n), y, z], dim=-1))


def sample_any_view_cameras(n: int, generator: torch.Generator | None = None,
                            distance: tuple[float, float] = (2.8, 5.0),
                            elevation_deg: tuple[float, float] = (10.0, 60.0)) -> Cameras:
    """Any view: full azimuth, elevation in `elevation_deg`, distance in `distance` (the seed's span)."""
    azimuth = 2.0 * math.pi * torch.rand(n, generator=generator)
    lo, hi = (math.radians(e) for e in elevation_deg)
    elevation = lo + (hi - lo) * torch.rand(n, generator=generator)
    radius = distance[0] + (distance[1] - distance[0]) * torch.rand(n, generator=generator)
    eye = torch.stack([radius * torch.cos(elevation) * torch.cos(azimuth),
                       radius * torch.cos(elevation) * torch.sin(azimuth),
                       radius * torch.sin(elevation)], dim=-1)
    return cameras_from_eyes(eye)
