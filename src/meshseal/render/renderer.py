"""The differentiable mesh renderer: rasterize -> interpolate -> texture -> Phong -> splat."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Protocol

import torch

from .. import threads
from ..mesh.core import Mesh
from .cameras import Cameras
from .interpolate import interpolate, scatter_to_image
from .lighting import PointLights
from .rasterizer import Fragments, rasterize
from .shader import PhongShader
from .texture import sample_textures


class Renderer(Protocol):
    """What every backend (ours, OpenGL, Blender, Mitsuba, ...) provides."""

    def render(self, mesh: Mesh, cameras: Cameras, lights: PointLights, width: int, height: int,
               background=(0.0, 0.0, 0.0)) -> torch.Tensor:
        """RGBA images (B, H, W, 4) in [0, 1], row 0 on top, one per camera."""


@dataclass
class MeshBatch:
    """B meshes of one size (or one mesh seen B times) ready for rendering.

    positions, normals: (B, V, 3) (B may be 1 to share); uvs: (B, V, 2) or None; faces: (F, 3) shared or
    (B, F, 3); face_material: (F,) or (B, F) indices into the material table: textures (list of (3, H, W)
    or None, or an (M, 3, H, W) stack), ambient/diffuse/specular (M, 3), shininess (M,).
    """

    positions: torch.Tensor
    normals: torch.Tensor
    uvs: torch.Tensor | None
    faces: torch.Tensor
    face_material: torch.Tensor
    textures: list | torch.Tensor
    ambient: torch.Tensor
    diffuse: torch.Tensor
    specular: torch.Tensor
    shininess: torch.Tensor = field(default=None)

    @classmethod
    def from_mesh(cls, mesh: Mesh) -> "MeshBatch":
        """One (possibly multi-material) mesh, shared by every camera of a batch."""
        materials = mesh.materials
        device = mesh.positions.device
        textures = [None if m.texture is None else m.texture.permute(2, 0, 1) for m in materials]
        return cls(mesh.positions.unsqueeze(0), mesh.normals.unsqueeze(0),
                   None if mesh.uvs is None else mesh.uvs.unsqueeze(0), mesh.faces, mesh.face_material,
                   textures, torch.stack([m.ambient for m in materials]).to(device),
                   torch.stack([m.diffuse for m in materials]).to(device),
                   torch.stack([m.specular for m in materials]).to(device),
                   torch.tensor([m.shininess for m in materials], device=device))

    def to(self, device) -> "MeshBatch":
        """This batch with every tensor on `device`."""
        def move(value):
            if isinstance(value, list):
                return [move(v) for v in value]
            return value.to(device) if isinstance(value, torch.Tensor) else value

        return type(self)(**{f.name: move(getattr(self, f.name)) for f in fields(self)})

    @classmethod
    def from_tensors(cls, positions: torch.Tensor, normals: torch.Tensor, uvs: torch.Tensor,
                     faces: torch.Tensor, textures: torch.Tensor) -> "MeshBatch":
        """B same-size meshes, mesh b textured by textures[b] (B, 3, H, W), default material."""
        from ..mesh.core import DEFAULT_AMBIENT, DEFAULT_DIFFUSE, DEFAULT_SHININESS, DEFAULT_SPECULAR

        n_batch, n_faces = positions.shape[0], faces.shape[-2]
        face_material = torch.arange(n_batch, device=positions.device).unsqueeze(1).expand(n_batch, n_faces)
        full = positions.new_full
        return cls(positions, normals, uvs, faces, face_material, textures, full((n_batch, 3), DEFAULT_AMBIENT),
                   full((n_batch, 3), DEFAULT_DIFFUSE), full((n_batch, 3), DEFAULT_SPECULAR),
                   full((n_batch,), DEFAULT_SHININESS))


@dataclass
class RenderOutput:
    """The render composited over the background: `color` (B, H, W, 3) and `alpha` (B, H, W); `fragments`
    for reuse (e.g. masks). `rgba` (B, H, W, 4) joins them when asked: most callers read `image` alone,
    and a registration makes thousands of renders, so none pays for the joined copy it does not read."""

    color: torch.Tensor
    alpha: torch.Tensor
    fragments: Fragments

    @property
    def rgba(self) -> torch.Tensor:
        """(B, H, W, 4): colour and coverage (made once, then kept)."""
        joined = self.__dict__.get("_rgba")
        if joined is None:
            joined = self.__dict__["_rgba"] = torch.cat([self.color, self.alpha.unsqueeze(-1)], dim=-1)
        return joined

    @property
    def image(self) -> torch.Tensor:
        """(B, 3, H, W), the layout the networks use."""
        return self.color.permute(0, 3, 1, 2)


def per_fragment(table: torch.Tensor, fragments: Fragments) -> torch.Tensor:
    """Look up a per-face (F,) or (B, F) table at the fragments."""
    if table.dim() == 1:
        return table[fragments.face]
    if table.shape[0] == 1:
        return table[0, fragments.face]
    return table[fragments.batch, fragments.face]


def splat_positions(fragments: Fragments) -> torch.Tensor:
    """Where each pixel's colour is splatted (B, H, W, 2): the surface point's screen position,
    barycentrics held fixed (see splatter). Background pixels have alpha 0 and splat nothing, so their
    positions are never read. Kept on fragments whose corners carry no gradient (renders of one
    rasterization under other lights, as the reading makes, share them)."""
    cached = getattr(fragments, "_splat_positions", None)
    if cached is not None:
        return cached
    surface_xy = (fragments.corners_xy * fragments.screen_bary.detach().unsqueeze(-1)).sum(1)
    positions = scatter_to_image(surface_xy, fragments, 0.0)
    if not fragments.corners_xy.requires_grad:  # no render of these fragments can want their gradient
        fragments._splat_positions = positions
    return positions


@dataclass
class MeshRenderer:
    """Composes the rasterizer and the Phong shader; `blend` is 'splat' (differentiable silhouettes,
    antialiased) or 'hard' (exact rasterized colours, as OpenGL without MSAA)."""

    shader: PhongShader = field(default_factory=PhongShader)
    blend: str = "splat"
    sigma: float = 0.5

    def __call__(self, batch: MeshBatch, cameras: Cameras, lights: PointLights, height: int, width: int,
                 background=(0.0, 0.0, 0.0), fragments: Fragments | None = None,
                 surface: tuple | None = None) -> RenderOutput:
        """Render B images; `background` is one RGB colour (3,) or one per image (B, 3). `fragments`: a
        rasterization of the same positions and cameras to reuse (re-shading a view skips rasterizing);
        `surface`: `surface` of the same mesh's geometry, textures and materials at those fragments
        (re-lighting it skips the lookups)."""
        threads.revisit()  # a long run of renders gives up a thread to jobs that started since (and takes it back)
        n_batch = len(cameras)
        dtype, device = batch.positions.dtype, batch.positions.device
        cameras, lights = cameras.to(device, dtype), lights.to(device, dtype)
        positions = batch.positions.expand(n_batch, -1, -1) if batch.positions.shape[0] == 1 else batch.positions
        if fragments is None:
            fragments = rasterize(cameras.world_to_clip(positions, width / height), batch.faces, height, width)
        lit = self.shade(batch, cameras, lights, fragments, surface)
        background = torch.as_tensor(background, dtype=dtype, device=device).reshape(-1, 3).expand(n_batch, 3)
        color = scatter_to_image(lit, fragments, 0.0)
        alpha = (fragments.pix_to_face >= 0).to(dtype)
        if self.blend == "hard":
            color = color + (1.0 - alpha.unsqueeze(-1)) * background[:, None, None, :]
            return RenderOutput(color, alpha, fragments)
        from .splatter import splat

        image, coverage = splat(color, alpha, splat_positions(fragments), background, self.sigma)
        return RenderOutput(image, coverage, fragments)

    def shade(self, batch: MeshBatch, cameras: Cameras, lights: PointLights, fragments: Fragments,
              surface: tuple | None = None) -> torch.Tensor:
        """The lit colour (P, 3) in [0, 1] of each fragment (before any blending); `surface`: `surface`
        of the same at these fragments, already looked up."""
        world, normal, albedo, material = surface if surface is not None else self.surface(batch, cameras, fragments)
        # index_select: on the CPU far cheaper than advanced indexing for these lookups.
        by_material = lambda table: table.index_select(0, material)  # noqa: E731
        by_image = lambda table: table.index_select(0, fragments.batch)  # noqa: E731
        lit = self.shader(world, normal, albedo, by_image(cameras.eye), by_image(lights.position),
                          by_image(lights.intensity), by_material(batch.ambient), by_material(batch.specular),
                          by_material(batch.shininess))
        return lit.clamp(0.0, 1.0)

    def surface(self, batch: MeshBatch, cameras: Cameras, fragments: Fragments) -> tuple:
        """What shading looks up at each fragment before any light: world position (P, 3), normal
        (P, 3), albedo times the diffuse colour (P, 3) and material (P,). It does not depend on the
        lights or the ambient colours: renders of one mesh under other lights can share it."""
        # One gather for every attribute: world position, normal and uv.
        n_batch = len(cameras)
        expand = lambda table: table.expand(n_batch, -1, -1) if table.shape[0] == 1 else table  # noqa: E731
        attributes = [expand(batch.positions), expand(batch.normals)]
        attributes += [] if batch.uvs is None else [expand(batch.uvs)]
        interpolated = interpolate(torch.cat(attributes, dim=-1), fragments)
        world, normal = interpolated[:, :3], interpolated[:, 3:6]
        material = per_fragment(batch.face_material, fragments)
        if batch.uvs is None:
            albedo = world.new_ones(world.shape[0], 3)
        else:
            albedo = sample_textures(batch.textures, interpolated[:, 6:8], material)
        return world, normal, albedo * batch.diffuse.index_select(0, material), material

    def render(self, mesh: Mesh, cameras: Cameras, lights: PointLights, width: int, height: int,
               background=(0.0, 0.0, 0.0)) -> torch.Tensor:
        """The `Renderer` protocol: RGBA (B, H, W, 4) of one mesh from each camera."""
        with torch.no_grad():
            return self(MeshBatch.from_mesh(mesh), cameras, lights, height, width, background).rgba
