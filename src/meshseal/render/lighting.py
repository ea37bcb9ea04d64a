"""Point lights with the seed's attenuation, and light samplers."""

from __future__ import annotations

from dataclasses import dataclass

import torch

# The seed's Phong constants (supplement, DiffRen section).
K_AMBIENT = 0.8
K_DIFFUSE = 1.4
K_SPECULAR = 0.0
ATTENUATION = (1.0, 0.07, 0.017)  # constant, linear, quadratic


@dataclass
class PointLights:
    """A batch of L point lights per image: position (B, L, 3) and RGB intensity (B, L, 3)."""

    position: torch.Tensor
    intensity: torch.Tensor

    def __len__(self) -> int:
        return self.position.shape[0]

    def to(self, device=None, dtype=None) -> "PointLights":
        return PointLights(self.position.to(device, dtype), self.intensity.to(device, dtype))

    def __getitem__(self, index) -> "PointLights":
        index = [index] if isinstance(index, int) else index
        return PointLights(self.position[index], self.intensity[index])


def lights_at(position: torch.Tensor, intensity: float = 1.0) -> PointLights:
    """One white light per image at `position` (B, 3)."""
    position = position.reshape(-1, 1, 3)
    return PointLights(position, torch.full_like(position, intensity))


def sample_seed_lights(n: int, generator: torch.Generator | None = None) -> PointLights:
    """The seed's training range: one point light at N((2, 1, 2), 0.2)."""
    mean = torch.tensor([2.0, 1.0, 2.0])
    return lights_at(mean + 0.2 * torch.randn(n, 3, generator=generator))


def sample_any_lights(n: int, generator: torch.Generator | None = None,
                      distance: tuple[float, float] = (2.0, 4.0)) -> PointLights:
    """A light anywhere on the upper hemisphere (z >= 0.1 r) at a distance in `distance`."""
    direction = torch.randn(n, 3, generator=generator)
    direction[:, 2] = direction[:, 2].abs() + 0.1 * direction.norm(dim=-1)
    direction = torch.nn.functional.normalize(direction, dim=-1)
    radius = distance[0] + (distance[1] - distance[0]) * torch.rand(n, 1, generator=generator)
    return lights_at(direction * radius)


def attenuation(distance: torch.Tensor) -> torch.Tensor:
    kc, kl, kq = ATTENUATION
    return kc + kl * distance + kq * distance * distance


__all__ = ["PointLights", "lights_at", "sample_seed_lights", "sample_any_lights", "attenuation",
           "K_AMBIENT", "K_DIFFUSE", "K_SPECULAR"]
