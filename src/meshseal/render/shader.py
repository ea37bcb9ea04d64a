"""Deferred Phong shading of fragments with point lights (the seed's DiffRen shading)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from .lighting import K_AMBIENT, K_DIFFUSE, K_SPECULAR, attenuation


@dataclass
class PhongShader:
    """color = ka*Ka*albedo + sum_lights I/att * (kd*max(n.l,0)*albedo + kr*Ks*max(r.v,0)^shininess).

    Normals are two-sided (flipped to face the camera). See docs/conventions.md.
    """

    k_ambient: float = K_AMBIENT
    k_diffuse: float = K_DIFFUSE
    k_specular: float = K_SPECULAR

    def __call__(self, position: torch.Tensor, normal: torch.Tensor, albedo: torch.Tensor, eye: torch.Tensor,
                 light_position: torch.Tensor, light_intensity: torch.Tensor, ambient: torch.Tensor,
                 specular: torch.Tensor, shininess: torch.Tensor) -> torch.Tensor:
        """Per-fragment inputs (P, 3) (lights (P, L, 3), shininess (P,)) -> colours (P, 3), unclamped."""
        normal = F.normalize(normal, dim=-1, eps=1e-12)
        to_eye = eye - position  # its length does not change which side faces the camera
        facing = torch.where((normal * to_eye).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(normal.dtype)
        normal = normal * facing
        color = self.k_ambient * ambient * albedo
        if not bool(light_intensity.any()) and not (torch.is_grad_enabled() and light_intensity.requires_grad):
            return color  # no light (an unlit albedo render): the light's terms would add exact zeros
        to_light = light_position - position.unsqueeze(1)  # (P, L, 3)
        distance = to_light.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        direction = to_light / distance
        n_dot_l = (normal.unsqueeze(1) * direction).sum(-1, keepdim=True)
        scale = light_intensity / attenuation(distance)
        color = color + (scale * self.k_diffuse * n_dot_l.clamp_min(0.0)).sum(1) * albedo
        if self.k_specular != 0.0:
            view = F.normalize(to_eye, dim=-1, eps=1e-12)
            reflected = 2.0 * n_dot_l * normal.unsqueeze(1) - direction
            r_dot_v = (reflected * view.unsqueeze(1)).sum(-1, keepdim=True).clamp_min(0.0)
            highlight = r_dot_v ** shininess.reshape(-1, 1, 1)
            color = color + (scale * self.k_specular * highlight).sum(1) * specular
        return color
