"""What an asset's import may have done to its textures before the picture was made, as the reading
predicts it.

An engine or a store rarely shows the textures the owner made: it caps their size (a 2048^2 texture
halved or quartered), block-compresses them for the GPU (BC1, the usual RGB format) or re-saves them as
JPEG; a converter or an importer that finds no normals in the file (trimesh between OBJ and GLB, a
glTF without them) recomputes them from the faces. Of the texture changes the size cap is the one the
reading has to predict: a halved texture keeps most of the
mark (it is smooth at the scale halving changes), but a picture of such an asset read against the
original's own textures leaves the detail the cap took in the residual, tens of times the mark (why
the codecs are not predicted: see `IMPORTS`). So the reading predicts the picture from the original's
textures as given and as each import in `IMPORTS` makes them, and `pick` keeps, per picture, the
candidate whose prediction explains the picture best; likewise the original's normals as given or as
recomputed from its faces (`pick_normals`): an authored normal (a hard edge, a bent normal) shades the
original otherwise than the recomputed one shades the asset, by more than the mark. Every pick looks at
the picture and the original only, never at a key, so the matched filter's p-values stay exact (no
correction for the candidates tried).

The texture functions work on 8-bit arrays (H, W, 3), as image files and GPUs hold them; the asset
attack `texture_half` of `evaluation.asset_attacks` is made of the same `resized`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

# A candidate is taken where its residual detail (the residual's energy after the whitening's high-pass)
# is under this share of that of the textures as given: a clear gain, not a coin toss between near-equals.
PICK_BELOW = 0.8
PICK_HIGHPASS = 1.5  # the high-pass of the residual the pick compares (Gaussian sigma, px)


def resized(texture: np.ndarray, factor: float) -> np.ndarray:
    """An 8-bit texture (H, W, 3) resized by `factor` (Pillow's antialiased bicubic, at least 4 texels)."""
    from PIL import Image

    height, width = texture.shape[:2]
    size = (max(4, round(width * factor)), max(4, round(height * factor)))
    return np.array(Image.fromarray(texture).resize(size, Image.Resampling.BICUBIC))


# The imports the reading tries, each a function of an 8-bit texture (H, W, 3): an engine's size cap.
# Not among them: block compression (BC1: read against the original compressed the same way, pictures
# of a BC1 asset read no better, the codec took the mark itself; BC7 changes a texture by about a
# level) and a JPEG re-save (it gained pictures of JPEG-saved textures, but pictures saved as JPEG
# picked it too and read worse; docs/results.md).
IMPORTS = {
    "halved": lambda texture: resized(texture, 0.5),
    "quartered": lambda texture: resized(texture, 0.25),
}


def to_bytes(texture: torch.Tensor) -> np.ndarray:
    """A texture (H, W, 3 or 4) of floats in [0, 1] -> 8-bit (H, W, 3), as an image file holds it."""
    return np.round(texture.detach().cpu().float()[..., :3].clamp(0, 1).numpy() * 255).astype(np.uint8)


def imported_textures(textures: list) -> dict[str, list]:
    """The textures (3, H, W) of a prepared original (None: untextured) as each import of `IMPORTS`
    makes them, by name; none that would leave a texture under 4 texels a side."""
    out = {}
    for name, change in IMPORTS.items():
        if name == "quartered" and any(t is not None and min(t.shape[-2:]) < 16 for t in textures):
            continue
        out[name] = [None if t is None else
                     torch.from_numpy(change(to_bytes(t.permute(1, 2, 0)))).to(t.device, t.dtype).permute(2, 0, 1).div(255.0).contiguous()
                     for t in textures]
    return out


@dataclass
class Imports:
    """A prepared original as an asset's import may have changed it: its textures as each import of
    `IMPORTS` makes them (`imported_textures`), and its vertex normals recomputed from the faces (B, V,
    3), None where those are the normals it has."""

    textures: dict[str, list]
    normals: torch.Tensor | None


# Normals recomputed from the faces are a candidate where some differ from the given ones by more than this
# (the length of the difference of unit vectors, about the angle in radians).
NORMALS_DIFFER = 0.05


def imported(original) -> Imports:
    """`Imports` of a prepared original (`render.MeshBatch` of one mesh)."""
    from ..mesh.preprocess import vertex_normals

    normals = None
    faces = original.faces if original.faces.dim() == 2 else original.faces[0]
    if original.positions.shape[0] == 1 and (original.faces.dim() == 2 or original.faces.shape[0] == 1):
        recomputed = vertex_normals(original.positions[0], faces)[None].to(original.normals)
        if float((recomputed - original.normals).norm(dim=-1).max()) > NORMALS_DIFFER:
            normals = recomputed
    return Imports(imported_textures(list(original.textures)), normals)


def _detail(residual: torch.Tensor, pixel: torch.Tensor, shape: tuple[int, int, int]) -> float:
    """The residual's (P, 3) energy after a Gaussian high-pass of PICK_HIGHPASS px, per pixel."""
    from ..models.spread import local_mean

    return float(((residual - local_mean(residual, pixel, shape, PICK_HIGHPASS)) ** 2).sum()) / max(1, len(residual))


def pick_normals(found, normals: torch.Tensor, cameras, shape: tuple[int, int, int]) -> bool:
    """Whether the recomputed `normals` (B, V, 3) predict one picture better than the original's own.

    `found` (`relight.RelitResidual` of the original as given): the original is shaded again with
    `normals` under the light fitted there, at the same fragments, and the change the normals make is
    added to the prediction, spread as the splatting renderer spreads a pixel's colour (a Gaussian of
    its sigma over the covered pixels); the high-passed residuals are then compared as `pick` compares
    textures (under PICK_BELOW of the given normals'). Only the picture and the original are looked at."""
    from ..models.spread import local_mean
    from ..render import MeshRenderer, interpolate

    if found.seen.shape[0] == 0:
        return False
    renderer = MeshRenderer()
    fragments, n_images = found.fragments, len(cameras)
    surface = found.surface if found.surface is not None else renderer.surface(found.relit, cameras, fragments)
    world, _, albedo, material = surface
    other = interpolate(normals.expand(n_images, -1, -1) if normals.shape[0] == 1 else normals, fragments)
    on = cameras.to(world.device, world.dtype)
    lights = found.lights.to(world.device, world.dtype)
    change = (renderer.shade(found.relit, on, lights, fragments, (world, other, albedo, material))
              - renderer.shade(found.relit, on, lights, fragments, surface))
    change = local_mean(change, fragments.pixel, shape, renderer.sigma).index_select(0, found.keep).to(found.seen)
    pixel = fragments.pixel.index_select(0, found.keep)
    given = found.seen - found.expected
    both = torch.cat([given, given - change], 1)
    detail = ((both - local_mean(both, pixel, shape, PICK_HIGHPASS)) ** 2).sum(0)
    return float(detail[3:].sum()) < PICK_BELOW * float(detail[:3].sum())


def beats_footprint(candidate, found, footprint, shape: tuple[int, int, int]) -> bool:
    """Whether the picked import's prediction (`candidate`, `relight.RelitResidual` from its textures,
    point samples) still explains the picture better than the textures as given under the footprint
    the picture shows for them (`footprint`: `reading.footprint.picture_footprint` of `found`, the
    given textures' residual): a picture halved or blurred after it was made loses the texture's detail
    too, which a smaller texture explains as well as the pixel's area does, but the mark there is the
    area's, not a point sample's. Taken where its detail is under PICK_BELOW of the footprint's."""
    pixel = found.fragments.pixel.index_select(0, found.keep)
    usable = footprint.usable
    given = _detail((found.seen - footprint.expected)[usable], pixel[usable], shape)
    picked = _detail(candidate.seen - candidate.expected, candidate.fragments.pixel.index_select(0, candidate.keep), shape)
    return picked < PICK_BELOW * given


def pick(found, textures: list, candidates: dict[str, list], shape: tuple[int, int, int]) -> str | None:
    """The import whose textures predict one picture best, or None for the textures as given.

    `found` (`relight.RelitResidual` of the original as given: the picture seen at its covered pixels,
    the prediction there, its albedo and texture coordinates), `textures` the original's (3, H, W) and
    `candidates` (`imported_textures`). Each candidate's prediction is the relit prediction with its
    albedo changed by what the import changed at each pixel's texture coordinates (times the shading
    there); the residual's detail (after a Gaussian high-pass of PICK_HIGHPASS px) is compared with
    that of the textures as given, and a candidate is taken where it is under PICK_BELOW of it. Only the
    picture and the original are looked at."""
    from ..models.spread import local_mean
    from ..render import sample_textures

    if not candidates or found.seen.shape[0] == 0:
        return None
    pixel = found.fragments.pixel.index_select(0, found.keep)
    shading = (found.expected / found.albedo.clamp_min(0.02)).clamp(0.0, 3.0)
    given = sample_textures(textures, found.uv, found.material)

    # Every candidate's residual side by side (P, 3 (1 + K)): one local mean for all of them.
    names = [None, *candidates]
    residuals = [found.seen - found.expected]
    for name in names[1:]:
        delta = sample_textures(candidates[name], found.uv, found.material) - given
        residuals.append(found.seen - (found.expected + shading * delta))
    stacked = torch.cat(residuals, 1)
    detail = ((stacked - local_mean(stacked, pixel, shape, PICK_HIGHPASS)) ** 2).sum(0)
    scores = dict(zip(names, detail.reshape(len(names), 3).sum(1).tolist()))
    best = min(scores, key=lambda name: scores[name])
    return best if best is not None and scores[best] < PICK_BELOW * scores[None] else None
