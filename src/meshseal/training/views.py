"""Views of a training or evaluation pass: cameras and lights, backgrounds, framing, pose jitter."""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from ..render import (
    Cameras,
)




def random_backgrounds(n: int, generator: torch.Generator) -> torch.Tensor:
    """Plain backgrounds: a random grey level, sometimes tinted, per picture."""
    grey = torch.rand(n, 1, generator=generator).expand(n, 3)
    tint = 0.15 * (torch.rand(n, 3, generator=generator) - 0.5)
    return (grey + tint).clamp(0.0, 1.0)




def jitter_cameras(cameras: Cameras, pixels: float, size: int, generator: torch.Generator) -> Cameras:
    """Move eye and look-at point by Gaussian noise worth about `pixels` pixels of a size x size
    picture at the look-at distance: the pose error a registration leaves."""
    if pixels <= 0:
        return cameras
    distance = (cameras.eye - cameras.at).norm(dim=-1, keepdim=True)
    sigma = pixels * 2.0 * distance * math.tan(math.radians(cameras.fov_y) / 2) / size
    shift = lambda: sigma * torch.randn(cameras.eye.shape, generator=generator).to(cameras.eye)  # noqa: E731
    return replace(cameras, eye=cameras.eye + shift(), at=cameras.at + shift())
