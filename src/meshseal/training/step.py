"""One pass of the whole pipeline on a batch: embed -> distort (3D) -> render -> distort (2D) -> frame
(blind decoders) or un-render onto the original's UV space (informed ones) -> decode. Shared by
training, validation and `meshseal eval` so they measure the same thing."""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from ..data.dataset import vertex_mask
from ..models import WatermarkModel
from ..render import (
    MeshBatch,
    MeshRenderer,
)
from .distortions import Distortions2D, Distortions3D
from .views import jitter_cameras
from ..render.views import sample_views


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
    decoded_input: torch.Tensor  # (B, 3, S, S) what the decoder saw (informed: UV maps (B, 10, G, G))
    vertex_mask: torch.Tensor | None  # (B, V) real vertices (None: no padding information)
    coverage: torch.Tensor  # (B, H, W) the marked object's interior pixels in the renders
    shown: torch.Tensor | None = None  # (B, 1, H, W) the texels a spread mark lay on (`batch_texels_used`)












def run_pass(model: WatermarkModel, batch: dict, message: torch.Tensor, renderer: MeshRenderer,
             generator: torch.Generator, render_size: int = 128, sampler: str = "seed",
             distortions_3d: Distortions3D | None = None, distortions_2d: Distortions2D | None = None,
             background: torch.Tensor | None = None, render_original: bool = True,
             unrender_jitter: float = 0.0, reference_mix: float = 0.0) -> PassOutput:
    """`unrender_jitter` (informed models): pose error in pixels of the camera used to un-render;
    `reference_mix`: weight of the exact original render in what the un-rendering subtracts (see
    `uv_maps`; 0 at evaluation and detection)."""
    from ..methods import method_for

    method = method_for(model)
    positions, normals, uvs, faces, texture = (batch[k] for k in ("positions", "normals", "uvs", "faces", "texture"))
    n = positions.shape[0]
    mask = vertex_mask(batch) if "n_verts" in batch else None
    normals_marked, uvs_marked, texture_marked, shown = method.mark_batch(batch, message, mask)
    height, width = (render_size, render_size) if isinstance(render_size, int) else render_size
    cameras, lights = sample_views(n, sampler, generator)
    if background is None:
        background = torch.zeros(n, 3)
    background = background.to(positions)
    distorted_positions, distorted_normals, distorted_faces = positions, normals_marked, faces
    state = generator.get_state()
    if distortions_3d is not None and method.informed:  # rigid moves are what registration recovers
        distortions_3d = replace(distortions_3d, p_rotation=0.0, p_scaling=0.0)
    if distortions_3d is not None:
        distorted_positions, distorted_normals, distorted_faces = distortions_3d(positions, normals_marked, faces, generator)
    marked = renderer(MeshBatch.from_tensors(distorted_positions, distorted_normals, uvs_marked, distorted_faces,
                                             texture_marked), cameras, lights, height, width, background)
    original_image = None
    if render_original:
        after = generator.get_state()
        generator.set_state(state)  # the same 3D distortion for the original
        with torch.no_grad():
            p, nr, f = positions, normals, faces
            if distortions_3d is not None:
                p, nr, f = distortions_3d(positions, normals, faces, generator)
            original_image = renderer(MeshBatch.from_tensors(p, nr, uvs, f, texture), cameras, lights,
                                      height, width, background).image
        generator.set_state(after)
    marked_image = marked.image
    picture, original_mesh, seen_from, distort = marked_image, None, cameras, distortions_2d
    if method.informed:  # the picture as saved, un-rendered from a camera off by `unrender_jitter`
        picture = marked_image if distortions_2d is None else distortions_2d(marked_image, generator)
        original_mesh = MeshBatch.from_tensors(positions, normals, uvs, faces, texture)
        seen_from, distort = jitter_cameras(cameras, unrender_jitter, height, generator), None
    framed, logits = method.read_batch(picture, marked.rgba[..., 3], original_mesh, seen_from, original_image,
                                       background, model.config.frame_size, distort, generator, reference_mix)
    return PassOutput(logits, message, texture, texture_marked, normals, normals_marked, uvs, uvs_marked,
                      original_image, marked_image, framed, mask, marked.rgba[..., 3].detach() > 0.999, shown)
