"""Un-rendering: carry a picture's pixels back onto the mesh's texture (UV) space.

Informed detection knows the mesh and (after registration) the camera of a picture, so every covered
pixel can be traced to the texel it shows. Averaging pixels per texel of a coarse UV grid turns a
picture from any view into the same canonical map, which a position-aware decoder reads.
"""

from __future__ import annotations

import torch

from .cameras import Cameras
from .interpolate import interpolate
from .rasterizer import Fragments, rasterize
from .renderer import per_fragment
from .texture import sample_textures


def surface_at_pixels(batch, cameras: Cameras, height: int, width: int) -> tuple[Fragments, torch.Tensor, torch.Tensor]:
    """Rasterize `batch` (a MeshBatch with uvs): fragments, their uv (P, 2) and unlit albedo (P, 3)."""
    n_batch = len(cameras)
    cameras = cameras.to(batch.positions.device, batch.positions.dtype)
    positions = batch.positions.expand(n_batch, -1, -1) if batch.positions.shape[0] == 1 else batch.positions
    fragments = rasterize(cameras.world_to_clip(positions, width / height), batch.faces, height, width)
    uv, albedo = surface_attributes(batch, fragments)
    return fragments, uv, albedo


def surface_attributes(batch, fragments: Fragments) -> tuple[torch.Tensor, torch.Tensor]:
    """uv (P, 2) and unlit albedo (P, 3) of `batch` (a MeshBatch with uvs) at its fragments."""
    n_batch = fragments.shape[0]
    uvs = batch.uvs.expand(n_batch, -1, -1) if batch.uvs.shape[0] == 1 else batch.uvs
    uv = interpolate(uvs, fragments)
    material = per_fragment(batch.face_material, fragments)
    albedo = sample_textures(batch.textures, uv, material) * batch.diffuse.index_select(0, material)
    return uv, albedo


def pixels_at(image: torch.Tensor, fragments: Fragments) -> torch.Tensor:
    """Image (B, C, H, W) -> its values at the foreground fragments (P, C)."""
    channels = image.shape[1]
    return image.permute(0, 2, 3, 1).reshape(-1, channels).index_select(0, fragments.pixel)


def surface_points(batch, fragments: Fragments, cameras: Cameras) -> tuple[torch.Tensor, torch.Tensor]:
    """Surface positions (P, 3) and unit normals (P, 3) at the fragments, the normals flipped to face
    the camera (two-sided shading)."""
    n_batch = fragments.shape[0]
    expand = lambda table: table.expand(n_batch, -1, -1) if table.shape[0] == 1 else table  # noqa: E731
    values = interpolate(torch.cat([expand(batch.positions), expand(batch.normals)], dim=-1), fragments)
    return values[:, :3], facing_camera(values[:, :3], values[:, 3:], cameras, fragments)


def facing_camera(position: torch.Tensor, normal: torch.Tensor, cameras: Cameras, fragments: Fragments) -> torch.Tensor:
    """Normals (P, 3) at the fragments' surface points (P, 3) made unit and flipped to face the camera
    (two-sided shading)."""
    unit = torch.nn.functional.normalize(normal, dim=-1)
    view = cameras.eye.to(position).index_select(0, fragments.batch) - position
    return torch.where((unit * view).sum(-1, keepdim=True) < 0, -unit, unit)


def unrender(values: torch.Tensor, uv: torch.Tensor, image_index: torch.Tensor, n_images: int, grid: int) -> torch.Tensor:
    """Per-fragment values (P, C) of images `image_index` (P,) at `uv` (P, 2) -> mean per cell of a
    grid x grid UV map, (n_images, C + 1, grid, grid).

    UVs wrap (REPEAT). The last channel is 1 where at least one pixel landed, 0 elsewhere; empty
    cells hold 0. Row 0 is v = 1, like the texture image.
    """
    channels = values.shape[1]
    wrapped = uv - torch.floor(uv)
    col = (wrapped[:, 0] * grid).long().clamp(0, grid - 1)
    row = ((1.0 - wrapped[:, 1]) * grid).long().clamp(0, grid - 1)
    cell = image_index * grid * grid + row * grid + col
    total = values.new_zeros(n_images * grid * grid, channels).index_add(0, cell, values)
    count = values.new_zeros(n_images * grid * grid, 1).index_add(0, cell, values.new_ones(len(cell), 1))
    maps = torch.cat([total / count.clamp_min(1.0), (count > 0).to(values.dtype)], dim=1)
    return maps.reshape(n_images, grid, grid, channels + 1).permute(0, 3, 1, 2)
