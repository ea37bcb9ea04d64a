"""The prediction made in linear light, for pictures another engine shaded.

Blender's engines (and game engines, web viewers) decode an 8-bit texture from sRGB to linear light,
shade it there, average each pixel's samples there (antialiasing, a film filter, mipmaps) and encode
the result back to sRGB. Our renderer shades the sRGB texture as it is. Where the shading changes from
face to face or a texture's detail is averaged within a pixel, the two differ by more than the mark,
and no local gain and offset of our prediction (`models.spread.local_affine`) takes that up. So a
picture our prediction misses by more than our own pictures mostly are (`TRY_ABOVE`) is predicted a
second time as such an engine would: the original's textures decoded to linear light, the picture
decoded likewise for the light fit, the relit render and its footprint (`picture_footprint`) made in
linear light and encoded to sRGB at the end; the prediction whose fine detail, once saved through the
picture's codec, misses the picture clearly less (`PICK_BELOW`) is read (`methods.spread`). Both look
at the picture and the original only, never at a key, so the matched filter's p-values stay exact.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from ..imaging import linear_to_srgb, srgb_to_linear

TRY_ABOVE = 1.5 / 255  # the sRGB prediction's fine-detail misfit (RMS) above which the linear one is tried
PICK_BELOW = 0.9  # the linear prediction is read where its fine-detail misfit energy is under this share of the sRGB one's
DETAIL_SIGMA = 1.5  # px: the local mean taken off both predictions' residuals before comparing them

_CHOSEN: list = []  # (picture, its version, footprint): the footprint one picture's linear prediction was made under


def chosen_before(image: torch.Tensor):
    """The footprint (`footprint.chosen_before`'s form) under which a reading of the one picture `image`
    (1, 3, H, W) made its linear prediction before, as long as the tensor is unchanged (a second look
    reads it again under other cameras; how the engine sampled it has not changed), or None."""
    from .kept import kept_with

    return kept_with(image, _CHOSEN)


def remember_choice(image: torch.Tensor, footprint) -> None:
    """Keep the `Footprint` (None: made without one) a reading of the one picture `image` made its
    linear prediction under, for `chosen_before`."""
    from .footprint import as_choice
    from .kept import keep_with

    keep_with(image, _CHOSEN, as_choice(footprint))


def linear_mesh(mesh):
    """`mesh` (MeshBatch) with its textures decoded to linear light."""
    textures = mesh.textures
    if torch.is_tensor(textures):
        return replace(mesh, textures=srgb_to_linear(textures))
    return replace(mesh, textures=[None if t is None else srgb_to_linear(t) for t in textures])


def detail_misfit(seen: torch.Tensor, expected: torch.Tensor, pixel: torch.Tensor, shape: tuple[int, int, int]) -> float:
    """Mean square (per pixel and channel) of the picture's fine detail (P, 3) a prediction (P, 3)
    leaves unexplained: the residual less its local mean (Gaussian, DETAIL_SIGMA px, over the object)."""
    from ..models.spread import local_mean

    residual = seen - expected
    detail = residual - local_mean(residual, pixel, shape, DETAIL_SIGMA)
    return float((detail * detail).mean()) if len(detail) else 0.0


def linear_prediction(mesh, image: torch.Tensor, cameras, footprint: bool, found, known=None):
    """The relit original (`reading.relight.relit_residual`) and its footprint (`picture_footprint`,
    where `footprint`) made in linear light, as (found, sampled) with the predictions encoded to sRGB
    and `found`'s picture and albedo (the sRGB ones) kept: one picture `image` (1, 3, H, W) of `mesh`
    seen by `cameras`. `found`: the sRGB reading's `RelitResidual` of the same picture. None where the
    linear render does not cover the same pixels. `known`: the footprint a reading of this picture chose
    for its linear prediction before (`chosen_before`), the only one tried then."""
    from .footprint import picture_footprint
    from .relight import relit_residual

    lit = linear_mesh(mesh)
    height, width = image.shape[-2], image.shape[-1]
    linear = relit_residual(lit, srgb_to_linear(image), cameras)
    if not torch.equal(linear.keep, found.keep):
        return None
    sampled = picture_footprint(lit, linear, cameras, height, width, known=known,
                                shortcut=False) if footprint else None
    encoded = replace(linear, seen=found.seen, albedo=found.albedo, expected=linear_to_srgb(linear.expected).to(found.expected))
    if sampled is not None:
        sampled = replace(sampled, expected=linear_to_srgb(sampled.expected).to(found.expected))
    return encoded, sampled
