"""The original relit to match a picture: the prediction informed reading subtracts, and the
picture un-rendered onto the original's UV grid (what the learned informed decoder reads)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F

from ..render import (
    Cameras,
    MeshBatch,
    MeshRenderer,
    interpolate,
    lights_at,
    pixels_at,
    relight_fragments,
    unrender,
)
from ..render.lighting import K_AMBIENT


@dataclass
class RelitResidual:
    """A picture's covered interior pixels next to the original mesh relit to match it: what the
    picture shows (P, 3), what the original predicts there (P, 3), its unlit albedo (P, 3), the
    texture coordinates (P, 2), material (P,) and picture index (P,) of each pixel, the `fragments`
    they were taken from (`keep` (P,) indexes them), and the fitted lighting: the original with the
    fitted ambient factors (`relit`) and the point `lights`."""

    seen: torch.Tensor
    expected: torch.Tensor
    albedo: torch.Tensor
    uv: torch.Tensor
    material: torch.Tensor
    image_index: torch.Tensor
    keep: torch.Tensor
    fragments: object
    relit: MeshBatch
    lights: object


_SURFACE = ("positions", "normals", "uvs", "faces", "face_material", "textures", "diffuse")  # `MeshRenderer.surface` reads


def _with_ambient_per_image(mesh: MeshBatch, ambient: torch.Tensor) -> MeshBatch:
    """`mesh` with the fitted ambient factors (B, 3), one per picture: B meshes with a material each
    take theirs; one mesh of M materials seen B times gets its material table repeated per picture."""
    n_images, n_materials = len(ambient), mesh.ambient.shape[0]
    if n_materials == n_images and (mesh.face_material.dim() == 2 or n_images == 1):
        return replace(mesh, ambient=ambient)
    material = mesh.face_material if mesh.face_material.dim() == 2 else mesh.face_material.expand(n_images, -1)
    offsets = n_materials * torch.arange(n_images, device=material.device).unsqueeze(1)
    return replace(mesh, face_material=material + offsets, textures=list(mesh.textures) * n_images,
                   ambient=ambient.repeat_interleave(n_materials, dim=0), diffuse=mesh.diffuse.repeat(n_images, 1),
                   specular=mesh.specular.repeat(n_images, 1), shininess=mesh.shininess.repeat(n_images))


def fitted_light(mesh: MeshBatch, image: torch.Tensor, cameras: Cameras, light_from: str = "all"):
    """`relit_residual`'s fit alone: the original with the fitted ambient factors, the point lights
    (the same numbers) and the rasterization they were fitted on (a render of the relit original from
    `cameras` can reuse it), without rendering the relit original (registration renders it itself)."""
    with torch.no_grad():
        fragments, relit, lights, _, _ = _fit(mesh, image, cameras, light_from)
        return relit, lights, fragments


def _fit(mesh: MeshBatch, image: torch.Tensor, cameras: Cameras, light_from: str):
    """The light fit of `relit_residual`: (fragments, relit mesh, lights, antialiased albedo (P, 3),
    and the surface the renders look up, `MeshRenderer.surface`, which relighting does not change)."""
    from ..render import rasterize

    n_images, height, width = len(cameras), image.shape[-2], image.shape[-1]
    unlit = replace(mesh, ambient=torch.full_like(mesh.ambient, 1.0 / K_AMBIENT))
    renderer = MeshRenderer()
    # the rasterization and surface lookups the render would make itself, kept for the relit render
    on = cameras.to(mesh.positions.device, mesh.positions.dtype)
    positions = mesh.positions.expand(n_images, -1, -1) if mesh.positions.shape[0] == 1 else mesh.positions
    fragments = rasterize(on.world_to_clip(positions, width / height), mesh.faces, height, width)
    surface = renderer.surface(unlit, on, fragments)
    flat = renderer(unlit, cameras, lights_at(cameras.eye, 0.0), height, width, fragments=fragments,
                    surface=surface)  # antialiased albedo
    albedo = pixels_at(flat.image, fragments)
    fit_on = flattest_half(flat.image, fragments) if light_from == "flat" else None
    _, ambient, lights = relight_fragments(mesh, fragments, cameras, pixels_at(image, fragments), albedo, fit_on,
                                           predict=False)
    return fragments, _with_ambient_per_image(mesh, ambient), lights, albedo, surface


def relit_residual(mesh: MeshBatch, image: torch.Tensor, cameras: Cameras, light_from: str = "all") -> RelitResidual:
    """Rasterize the original `mesh` from `cameras` over the picture (B, 3, H, W), fit a point light
    that explains the picture from the original texture (`relight_fragments`) and render the original
    under it. Silhouette pixels (partly background) are left out. `light_from` "flat" fits the light on
    the half of the object's pixels where the albedo is flattest (`flattest_half`): a camera a pixel or
    two off then barely changes what the fit sees (registration refines such cameras)."""
    from ..render.renderer import per_fragment

    n_images, height, width = len(cameras), image.shape[-2], image.shape[-1]
    with torch.no_grad():
        fragments, relit, lights, albedo, surface = _fit(mesh, image, cameras, light_from)
        uv = interpolate(mesh.uvs.expand(n_images, -1, -1) if mesh.uvs.shape[0] == 1 else mesh.uvs, fragments)
        same = all(getattr(relit, name) is getattr(mesh, name) for name in _SURFACE)  # only the ambient refitted
        relit_render = MeshRenderer()(relit, cameras, lights, height, width, fragments=fragments,
                                      surface=surface if same else None)
        inside = pixels_at(relit_render.rgba[..., 3:].permute(0, 3, 1, 2), fragments)[:, 0] > 0.999
        keep = torch.nonzero(inside).squeeze(1)
        pick = lambda values: values.index_select(0, keep)  # noqa: E731
        return RelitResidual(pick(pixels_at(image, fragments)).to(image), pick(pixels_at(relit_render.image, fragments)).to(image),
                             pick(albedo).to(image), pick(uv).to(image), pick(per_fragment(mesh.face_material, fragments)),
                             pick(fragments.batch), keep, fragments, relit, lights)


def flattest_half(albedo: torch.Tensor, fragments, reach: int = 2) -> torch.Tensor:
    """Which covered pixels of `fragments` (P,) lie where the albedo render (B, 3, H, W) varies least
    within `reach` pixels: the flatter half of each image's pixels, by rank. Steps to the next pixel
    measure the variation (a central difference misses stripes one pixel wide)."""
    step_x = F.pad((albedo[..., :, 1:] - albedo[..., :, :-1]).abs(), (0, 1))
    step_y = F.pad((albedo[..., 1:, :] - albedo[..., :-1, :]).abs(), (0, 0, 0, 1))
    activity = (step_x + step_y).amax(1, keepdim=True)
    activity = pixels_at(F.max_pool2d(activity, 2 * reach + 1, 1, reach), fragments)[:, 0]
    flat = torch.zeros_like(activity, dtype=torch.bool)
    for index in torch.unique(fragments.batch).tolist():
        chosen = torch.nonzero(fragments.batch == index).squeeze(1)
        flat[chosen[activity[chosen].argsort(stable=True)[: (len(chosen) + 1) // 2]]] = True
    return flat


def uv_maps(mesh: MeshBatch, image: torch.Tensor, cameras: Cameras, grid: int, reference: torch.Tensor | None = None,
            reference_mix: float = 0.0) -> torch.Tensor:
    """What the learned informed decoder reads: the picture (B, 3, H, W) seen from `cameras`,
    un-rendered onto the original mesh's UV grid -> (B, 10, grid, grid).

    Channels: the residual left by the relit original (x10: mostly the watermark; `relit_residual`),
    the picture (3), the original albedo (3), coverage (1). Training may blend in the exact `reference`
    (the original rendered under the picture's own light) with weight `reference_mix`: a curriculum.
    """
    found = relit_residual(mesh, image, cameras)
    expected = found.expected
    if reference is not None and reference_mix > 0:
        exact = pixels_at(reference, found.fragments).index_select(0, found.keep).to(image)
        expected = reference_mix * exact + (1.0 - reference_mix) * expected
    seen = pixels_at(image, found.fragments).index_select(0, found.keep)  # differentiable in the picture
    values = torch.cat([10.0 * (seen - expected), seen, found.albedo], dim=1)
    return unrender(values, found.uv, found.image_index, len(cameras), grid)
