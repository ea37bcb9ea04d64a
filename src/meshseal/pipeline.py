"""One pass of the whole pipeline on a batch: embed -> distort (3D) -> render -> frame -> distort (2D)
-> decode. Shared by training, validation and `meshseal eval` so they measure the same thing."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .data.dataset import vertex_mask
from .distortions import Distortions2D, Distortions3D
from .framing import boxes_from_mask, crop_boxes
from .models import WatermarkModel
from .render import MeshBatch, MeshRenderer, sample_any_lights, sample_any_view_cameras, sample_seed_cameras, sample_seed_lights


@dataclass
class PassOutput:
    logits: torch.Tensor
    message: torch.Tensor
    texture: torch.Tensor
    texture_marked: torch.Tensor
    normals: torch.Tensor
    normals_marked: torch.Tensor
    uvs: torch.Tensor
    uvs_marked: torch.Tensor
    render: torch.Tensor  # (B, 3, H, W) original
    render_marked: torch.Tensor  # (B, 3, H, W) watermarked, before 2D distortions
    decoded_input: torch.Tensor  # (B, 3, S, S) what the decoder saw
    vertex_mask: torch.Tensor | None  # (B, V) real vertices (None: no padding information)


def sample_views(n: int, sampler: str, generator: torch.Generator):
    """Cameras and lights from the seed's ranges ('seed') or from anywhere ('any')."""
    if sampler == "seed":
        return sample_seed_cameras(n, generator), sample_seed_lights(n, generator)
    if sampler == "any":
        return sample_any_view_cameras(n, generator), sample_any_lights(n, generator)
    raise ValueError(f"unknown view sampler '{sampler}' (seed | any)")


def random_backgrounds(n: int, generator: torch.Generator) -> torch.Tensor:
    """Plain backgrounds: a random grey level, sometimes tinted, per picture."""
    grey = torch.rand(n, 1, generator=generator).expand(n, 3)
    tint = 0.15 * (torch.rand(n, 3, generator=generator) - 0.5)
    return (grey + tint).clamp(0.0, 1.0)


def frame(image: torch.Tensor, alpha: torch.Tensor, size: int, background: torch.Tensor) -> torch.Tensor:
    """Crop the object's bounding box (from the coverage) into a square size x size picture."""
    boxes = boxes_from_mask(alpha.detach().cpu() > 0.5)
    return crop_boxes(image, boxes, size, background.to(image))


def run_pass(model: WatermarkModel, batch: dict, message: torch.Tensor, renderer: MeshRenderer,
             generator: torch.Generator, render_size: int = 128, sampler: str = "seed",
             distortions_3d: Distortions3D | None = None, distortions_2d: Distortions2D | None = None,
             background: torch.Tensor | None = None, render_original: bool = True) -> PassOutput:
    positions, normals, uvs, faces, texture = (batch[k] for k in ("positions", "normals", "uvs", "faces", "texture"))
    n = positions.shape[0]
    mask = vertex_mask(batch) if "n_verts" in batch else None
    normals_marked, uvs_marked, texture_marked = model.embed(positions, normals, uvs, texture, message, mask)
    cameras, lights = sample_views(n, sampler, generator)
    if background is None:
        background = torch.zeros(n, 3)
    background = background.to(positions)
    distorted_positions, distorted_normals, distorted_faces = positions, normals_marked, faces
    state = generator.get_state()
    if distortions_3d is not None:
        distorted_positions, distorted_normals, distorted_faces = distortions_3d(positions, normals_marked, faces, generator)
    marked = renderer(MeshBatch.from_tensors(distorted_positions, distorted_normals, uvs_marked, distorted_faces,
                                             texture_marked), cameras, lights, render_size, render_size, background)
    original_image = None
    if render_original:
        after = generator.get_state()
        generator.set_state(state)  # the same 3D distortion for the original
        with torch.no_grad():
            p, nr, f = positions, normals, faces
            if distortions_3d is not None:
                p, nr, f = distortions_3d(positions, normals, faces, generator)
            original_image = renderer(MeshBatch.from_tensors(p, nr, uvs, f, texture), cameras, lights,
                                      render_size, render_size, background).image
        generator.set_state(after)
    marked_image = marked.image
    framed = frame(marked_image, marked.rgba[..., 3], model.config.frame_size, background)
    if distortions_2d is not None:
        framed = distortions_2d(framed, generator)
    logits = model.decode(framed)
    return PassOutput(logits, message, texture, texture_marked, normals, normals_marked, uvs, uvs_marked,
                      original_image, marked_image, framed, mask)
