"""Cached G-buffers: train a texture-only mark without rasterizing in the training step.

A texture-only mark never moves the geometry, so for a (mesh, camera, light) view everything the
renderer computes except the texture lookup is fixed: which texel each pixel shows (its uv), how much
light reaches it (the Phong factor of a white light on a grey material, the same for every channel)
and whether the object covers it. `bake` rasterizes those once per view with meshseal's own
rasterizer and shader, framed as `meshseal detect` frames a picture (the object's square bounding
box plus `framing.BOX_MARGIN`, filling a `size` x `size` frame: the same as rendering large and
cropping around the object). A training step is then `composite`: a bilinear texture lookup times
the shade over the mask, background elsewhere — pure tensor work that runs at GPU speed with no host
round trip, where the rendering pass rasterizes on the CPU for every picture.

`composite(texture, bake(...))` equals `MeshRenderer(blend="hard")` of the same view (tested): the
cache changes the speed of training, not what it sees. 3D distortions (noise, rotation, scaling,
cropping) are drawn per view at bake time, so a view bank of K views per mesh holds K draws.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..data.dataset import collate, vertex_mask
from ..mesh.core import DEFAULT_AMBIENT, DEFAULT_DIFFUSE, DEFAULT_SHININESS
from ..reading.framing import BOX_MARGIN
from ..render import interpolate, rasterize, scatter_to_image
from ..render.shader import PhongShader


@dataclass
class GBuffers:
    """N baked views: uv (N, S, S, 2) texture coordinates wrapped to [0, 1) (0 off the object), shade
    (N, S, S) the lighting factor (0 off the object), mask (N, S, S) bool, item (N,) long: the dataset
    item each view shows."""

    uv: torch.Tensor
    shade: torch.Tensor
    mask: torch.Tensor
    item: torch.Tensor
    surface: "Surface | None" = None  # what a mark that moves normals or uvs needs (`bake_views(surface=True)`)

    def __len__(self) -> int:
        return self.item.shape[0]

    def to(self, device, dtype=None) -> "GBuffers":
        float_type = dtype or self.uv.dtype
        return GBuffers(self.uv.to(device, float_type), self.shade.to(device, float_type), self.mask.to(device),
                        self.item.to(device), None if self.surface is None else self.surface.to(device, float_type))

    def __getitem__(self, index) -> "GBuffers":
        return GBuffers(self.uv[index], self.shade[index], self.mask[index], self.item[index],
                        None if self.surface is None else self.surface[index])


    def save(self, path, meta: dict) -> None:
        """Compressed .npz (uv and shade as float16), written atomically."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        temp = path.with_name(f".{path.name}.{os.getpid()}.tmp.npz")  # processes baking the same bank at once each write their own
        extra = {} if self.surface is None else {
            "face": self.surface.face.numpy().astype(np.int32), "bary": self.surface.bary.to(torch.float16).numpy(),
            "world": self.surface.world.to(torch.float16).numpy(), "eye": self.surface.eye.numpy(),
            "light_position": self.surface.light_position.numpy(), "light_intensity": self.surface.light_intensity.numpy()}
        np.savez_compressed(temp, uv=self.uv.to(torch.float16).numpy(), shade=self.shade.to(torch.float16).numpy(),
                            mask=np.packbits(self.mask.numpy(), axis=-1), item=self.item.numpy().astype(np.int32),
                            meta=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8), **extra)
        temp.replace(path)

    @classmethod
    def load(cls, path) -> tuple["GBuffers", dict]:
        with np.load(path) as data:
            size = data["uv"].shape[-2]
            mask = np.unpackbits(data["mask"], axis=-1, count=size).astype(bool)
            meta = json.loads(bytes(data["meta"]).decode())
            surface = None
            if "face" in data:
                surface = Surface(*(torch.from_numpy(data[name]) for name in
                                    ("face", "bary", "world", "eye", "light_position", "light_intensity")))
            return cls(torch.from_numpy(data["uv"]), torch.from_numpy(data["shade"]), torch.from_numpy(mask),
                       torch.from_numpy(data["item"].astype(np.int64)), surface), meta


@dataclass
class Surface:
    """Per pixel of N baked views: the visible face (N, S, S) (-1 off the object), its perspective-
    correct barycentrics (N, S, S, 3) and the surface point (N, S, S, 3); per view the eye (N, 3) and the
    lights (N, L, 3) position and intensity. Positions never move under a vertex mark that changes
    normals or uvs, so these stay valid while the mark re-shades and re-textures the pixels
    (`composite_surface`)."""

    face: torch.Tensor
    bary: torch.Tensor
    world: torch.Tensor
    eye: torch.Tensor
    light_position: torch.Tensor
    light_intensity: torch.Tensor

    def to(self, device, dtype=None) -> "Surface":
        cast = lambda t: t.to(device, dtype or t.dtype)  # noqa: E731
        return Surface(self.face.to(device), cast(self.bary), cast(self.world), cast(self.eye),
                       cast(self.light_position), cast(self.light_intensity))

    def __getitem__(self, index) -> "Surface":
        return Surface(*(getattr(self, name)[index] for name in
                         ("face", "bary", "world", "eye", "light_position", "light_intensity")))


def frame_clip(clip: torch.Tensor, valid: torch.Tensor, margin: float = BOX_MARGIN) -> torch.Tensor:
    """Clip coordinates (B, V, 4) moved so that the square box around the `valid` (B, V) vertices'
    projections, widened by `margin` of its side each way, fills the picture: the clip coordinates of
    rendering the whole view and cropping that box (`framing.boxes_from_mask`) out of it."""
    ndc = clip[..., :2] / clip[..., 3:4]
    big = torch.finfo(clip.dtype).max
    low = torch.where(valid[..., None], ndc, big).amin(1)
    high = torch.where(valid[..., None], ndc, -big).amax(1)
    centre = (low + high) / 2
    half = ((high - low).amax(1) / 2 * (1 + 2 * margin)).clamp_min(1e-3)
    xy = (clip[..., :2] - centre[:, None] * clip[..., 3:4]) / half[:, None, None]
    return torch.cat([xy, clip[..., 2:]], dim=-1)


def bake_views(batch: dict, cameras, lights, size: int, framed: bool = True, distortions_3d=None,
               generator: torch.Generator | None = None, surface: bool = False) -> GBuffers:
    """G-buffers of B dataset items (a `collate`d batch), one view each from `cameras` and `lights`;
    with `surface`, also what `composite_surface` needs to re-shade them under changed normals and uvs."""
    positions, normals, faces = batch["positions"], batch["normals"], batch["faces"]
    if distortions_3d is not None:
        positions, normals, faces = distortions_3d(positions, normals, faces, generator)
    clip = cameras.world_to_clip(positions, 1.0)
    if framed:
        used = torch.zeros(positions.shape[:2], dtype=torch.bool)
        used.scatter_(1, faces.reshape(faces.shape[0], -1), True)  # cropped faces leave their vertices out
        clip = frame_clip(clip, used & (vertex_mask(batch) > 0))
    fragments = rasterize(clip, faces, size, size)
    values = interpolate(torch.cat([positions, normals, batch["uvs"]], dim=-1), fragments)
    ones = values.new_ones(values.shape[0], 3)
    by_image = lambda table: table.index_select(0, fragments.batch)  # noqa: E731
    shade = PhongShader()(values[:, :3], values[:, 3:6], DEFAULT_DIFFUSE * ones, by_image(cameras.eye),
                          by_image(lights.position), by_image(lights.intensity), DEFAULT_AMBIENT * ones, 0 * ones,
                          values.new_full((values.shape[0],), DEFAULT_SHININESS))[:, 0]
    uv = values[:, 6:8] - torch.floor(values[:, 6:8])
    found = None
    if surface:
        found = Surface(fragments.pix_to_face.to(torch.int32), scatter_to_image(fragments.bary, fragments, 0.0),
                        scatter_to_image(values[:, :3], fragments, 0.0), cameras.eye.clone(),
                        lights.position.clone(), lights.intensity.clone())
    return GBuffers(scatter_to_image(uv, fragments, 0.0), scatter_to_image(shade[:, None], fragments, 0.0)[..., 0],
                    fragments.pix_to_face >= 0, torch.zeros(positions.shape[0], dtype=torch.long), found)


def bake(dataset, views: int, size: int, sampler: str = "seed", seed: int = 0, distortions_3d=None,
         batch_size: int = 16, progress=None, surface: bool = False, workers: int = 0) -> GBuffers:
    """`views` framed views of every item of `dataset` (cameras and lights from `sampler`'s ranges);
    `surface`: with what a vertex mark needs (`Surface`). The items are baked in chunks of
    `batch_size` per view, each chunk drawing its cameras, lights and 3D distortions from its own
    generator (seeded by `seed`, the view and the chunk), so `workers` spawned one-thread processes
    (0: this process) bake the same bank as one process does."""
    chunks = [(dataset, view, list(range(start, min(len(dataset), start + batch_size))), size, sampler, seed,
               distortions_3d, surface) for view in range(views) for start in range(0, len(dataset), batch_size)]
    from ..data.build import _executor

    parts = []
    with _executor(min(workers, len(chunks)) if len(chunks) > 1 else 0) as pool:  # 0: this process, in turn
        for future, chunk in zip([pool.submit(_bake_chunk, *chunk) for chunk in chunks], chunks):
            parts.append(future.result())
            if progress is not None:
                progress(len(chunk[2]))
    found = None
    if surface:
        found = Surface(*(torch.cat([getattr(p.surface, name) for p in parts]) for name in
                          ("face", "bary", "world", "eye", "light_position", "light_intensity")))
    return GBuffers(*(torch.cat([getattr(p, name) for p in parts]) for name in ("uv", "shade", "mask", "item")), found)


@torch.no_grad()
def _bake_chunk(dataset, view: int, index: list[int], size: int, sampler: str, seed: int, distortions_3d,
                surface: bool) -> GBuffers:
    """One chunk of `bake`: the items `index` in one view each, drawn from the chunk's own generator."""
    from ..render.views import sample_views

    generator = torch.Generator().manual_seed(((seed * 1_000_003 + view) * 1_000_033 + index[0]) % 2 ** 63)
    batch = collate([_geometry(dataset, i) for i in index])
    cameras, lights = sample_views(len(index), sampler, generator)
    part = bake_views(batch, cameras, lights, size, True, distortions_3d, generator, surface)
    if part.surface is not None:
        part.surface.bary, part.surface.world = part.surface.bary.half(), part.surface.world.half()
    return GBuffers(part.uv.half(), part.shade.half(), part.mask, torch.tensor(index), part.surface)


def _geometry(dataset, index: int) -> dict:
    """An item without its texture (reading textures is most of an item's cost)."""
    geometry = getattr(dataset, "geometry", None)
    if geometry is not None and index in geometry:  # `train.CachedItems`
        return geometry[index]
    return {k: v for k, v in dataset[index].items() if k != "texture"}


def cached_bake(dataset, path, views: int, size: int, sampler: str, seed: int, distortions_3d=None,
                log=print, surface: bool = False, workers: int = 0) -> GBuffers:
    """`bake` (in `workers` processes), kept in `path` (a .npz) and reused while the dataset's items (a
    `MeshDataset` or a Subset of one) and the settings are the same."""
    if isinstance(dataset, torch.utils.data.Subset):
        ids = [dataset.dataset.rows[i]["id"] for i in dataset.indices]
    else:
        ids = [row["id"] for row in dataset.rows]
    meta = {"format": 2, "ids": hashlib.sha256("\n".join(ids).encode()).hexdigest(), "views": views, "size": size,
            "sampler": sampler, "seed": seed, "margin": BOX_MARGIN, "surface": surface,
            "distortions_3d": None if distortions_3d is None else vars(distortions_3d)}
    path = Path(path)
    if path.is_file():
        buffers, stored = GBuffers.load(path)
        if stored == meta:
            return buffers
        log(f"{path}: baked for other settings, baking again")
    from tqdm import tqdm

    with tqdm(total=views * len(dataset), desc=f"baking {path.name}", unit="view", dynamic_ncols=True) as bar:
        buffers = bake(dataset, views, size, sampler, seed, distortions_3d, progress=bar.update, surface=surface,
                       workers=workers)
    buffers.save(path, meta)
    return buffers


def bake_key(split: str, kinds, views: int, size: int, sampler: str, seed: int, distortion_3d: float,
             surface: bool = False) -> str:
    """A file name for one bank of views of a dataset folder."""
    text = json.dumps([split, sorted(kinds or []), views, size, sampler, seed, distortion_3d] + ([True] if surface else []))
    return f"{split}-{hashlib.sha256(text.encode()).hexdigest()[:12]}.npz"


def _sample(texture: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Textures (B, C, T, T') at uv (B, S, S, 2): bilinear, REPEAT wrapping, texel centres (as
    `render.sample_texture` and OpenGL) -> (B, C, S, S)."""
    height, width = texture.shape[-2:]
    padded = F.pad(texture, (1, 1, 1, 1), mode="circular")
    uv = uv.to(texture.dtype)
    x = (uv[..., 0] * width + 1.0) / (width + 2) * 2.0 - 1.0
    y = ((1.0 - uv[..., 1]) * height + 1.0) / (height + 2) * 2.0 - 1.0
    return F.grid_sample(padded, torch.stack([x, y], dim=-1), mode="bilinear", padding_mode="border",
                         align_corners=False)


def composite_surface(texture: torch.Tensor, normals: torch.Tensor, uvs: torch.Tensor, faces: torch.Tensor,
                      buffers: GBuffers, background: torch.Tensor) -> torch.Tensor:
    """The pictures (B, 3, S, S) of B meshes whose vertex normals (B, V, 3) and uvs (B, V, 2) a mark may
    have changed, faces (B, F, 3), in the baked views `buffers` (baked with `surface=True`): the
    normals and uvs interpolated at each pixel's face and barycentrics, the Phong shade recomputed, the
    texture (B, 3, T, T) looked up. Equals the hard render of those meshes; differentiable in the
    texture, normals and uvs."""
    found = buffers.surface
    n, size = found.face.shape[0], found.face.shape[-1]
    corner = torch.gather(faces, 1, found.face.long().clamp_min(0).reshape(n, -1, 1).expand(-1, -1, 3))
    weights = found.bary.to(normals.dtype).reshape(n, -1, 3, 1)

    def at_pixels(table):  # (B, V, C) -> (B, S * S, C)
        channels = table.shape[-1]
        values = torch.gather(table, 1, corner.reshape(n, -1, 1).expand(-1, -1, channels))
        return (values.reshape(n, -1, 3, channels) * weights).sum(2)

    normal, uv = at_pixels(normals).reshape(-1, 3), at_pixels(uvs)
    pixels = size * size
    per_pixel = lambda table: table.repeat_interleave(pixels, dim=0)  # noqa: E731
    ones = normal.new_ones(normal.shape[0], 3)
    shade = PhongShader()(found.world.to(normal.dtype).reshape(-1, 3), normal, DEFAULT_DIFFUSE * ones,
                          per_pixel(found.eye.to(normal.dtype)), per_pixel(found.light_position.to(normal.dtype)),
                          per_pixel(found.light_intensity.to(normal.dtype)), DEFAULT_AMBIENT * ones, 0 * ones,
                          normal.new_full((normal.shape[0],), DEFAULT_SHININESS))[:, 0].reshape(n, 1, size, size)
    uv = (uv - torch.floor(uv.detach())).reshape(n, size, size, 2)
    colour = (_sample(texture, uv) * shade.to(texture.dtype)).clamp(0.0, 1.0)
    return torch.where(buffers.mask.unsqueeze(1), colour, background.to(colour)[:, :, None, None])


def composite(texture: torch.Tensor, buffers: GBuffers, background: torch.Tensor) -> torch.Tensor:
    """The pictures (B, 3, S, S) of textures (B, 3, T, T) in the baked views `buffers` (B of them) over
    `background` (B, 3): the texture sampled bilinearly with REPEAT wrapping at texel centres (as
    `render.sample_texture` and OpenGL), times the shade, clamped to [0, 1]. Differentiable in the
    texture."""
    colour = (_sample(texture, buffers.uv) * buffers.shade.to(texture.dtype).unsqueeze(1)).clamp(0.0, 1.0)
    return torch.where(buffers.mask.unsqueeze(1), colour, background.to(colour)[:, :, None, None])
