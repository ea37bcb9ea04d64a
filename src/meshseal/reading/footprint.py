"""How a picture sampled the object: point samples, or each pixel's area blurred (`picture_footprint`),
and the linear-light part of a residual that a tone curve leaves (`take_off_linear_light`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..render import (
    Cameras,
    MeshBatch,
    MeshRenderer,
)
from .kept import keep_with, kept_with
from .relight import RelitResidual

FOOTPRINT_SIGMAS = (0.35, 0.5, 0.75, 1.0)
RESAMPLED = (0.5, 0.75, 1.5)  # a picture rendered at 1/factor its size and resized (bicubic, antialiased)
RESAMPLED_TEMPLATE_SIGMA = 0.25  # px: the area footprint that stands for a resized picture's filter (docs/reading.md)
AREA_TEMPLATE_SCALE = 0.5  # the template of a picture read under a blurred area footprint: that blur times this (docs/reading.md)
RESAMPLED_LARGEST = 1024  # px: no resized prediction is rendered larger than this a side
RESAMPLED_ADJOINT = True  # a resized picture's template: the resize's own adjoint (else the area blurred as above)
LINEAR_LIGHT_SIGMA = 2.0  # px: window of the residual's variance along and across light added in linear light
LINEAR_LIGHT_RATIO = 1.0  # taken off fully where the variance along it is this many times that across
LINEAR_LIGHT_DISTINCT = 0.05  # and where its direction differs this much (sine) from the brightness's


@dataclass
class Footprint:
    """How a picture sampled the surface, as far as the original's texture shows: per picture, point
    samples at pixel centres (our renderer, OpenGL without multisampling) or the average over each
    pixel's area blurred by a Gaussian of `sigma` pixels (antialiasing and pixel filters of Blender and
    game engines, mipmaps, resizing, blur), or rendered at another size and resized (`resized`).
    `expected` (P, 3): the relit original under each picture's
    footprint at the kept pixels; `usable` (P,): the kept pixels that footprint covers wholly; `sigma`
    (B,): NaN for point samples. `fragments`: the rasterization `scale` times finer that sampled each
    pixel's area, and `parent` (F,): the picture pixel (flat index into B*H*W) of each of its
    fragments; the matched filter's template is built from them (None where every picture is read
    with point samples and they were not formed)."""

    expected: torch.Tensor
    usable: torch.Tensor
    sigma: torch.Tensor
    fragments: object
    parent: torch.Tensor | None
    scale: int
    resized: torch.Tensor | None = None  # (B,): the factor a picture was found resized by (NaN: not resized)


def supersampling(height: int, width: int) -> int:
    """Sub-pixel samples per picture pixel along each axis for `picture_footprint`: 4 up to 256^2,
    fewer for larger pictures (whose pixels cover less texture) to bound the render to about 1024^2."""
    return max(1, min(4, 1024 // max(height, width)))


def pick_full(image: torch.Tensor, pixel: torch.Tensor) -> torch.Tensor:
    """Images (B, 3, H, W) at flat pixel indices into (B, H, W) -> (P, 3)."""
    return image.permute(0, 2, 3, 1).reshape(-1, 3).index_select(0, pixel)


def resampled_prediction(relit: MeshBatch, cameras: Cameras, lights, height: int, width: int,
                         factor: float) -> torch.Tensor:
    """The relit original as a picture rendered at 1/`factor` of `height` x `width` (point samples)
    and then resized to it, bicubic with antialiasing (as image tools resize: torch's filter matches
    Pillow's) -> (B, 3, H, W)."""
    render = MeshRenderer()(relit, cameras, lights, *resized_source_size(height, width, factor)).image
    return F.interpolate(render, size=(height, width), mode="bicubic", antialias=True, align_corners=False)


def resized_source_size(height: int, width: int, factor: float) -> tuple[int, int]:
    """The size a picture of `height` x `width` had before it was resized by `factor`."""
    return max(8, round(height / factor)), max(8, round(width / factor))


def resized_adjoint(canvas: torch.Tensor, factor: float) -> torch.Tensor:
    """The adjoint of `resampled_prediction`'s resize: values on the resized picture's pixels
    (B, C, H, W) carried back onto the pixels of the picture before it (B, C, h, w), each weighted as
    the bicubic, antialiased resize weighted it into the pixels it made. A residual so carried back
    and summed per cell of the source render is the matched filter of a mark that the resize blurred
    (the template is then the resize's own filter, not a Gaussian that stands in for it)."""
    size = resized_source_size(canvas.shape[-2], canvas.shape[-1], factor)
    # autograd's own backward of the resize, also where the reading runs under inference mode (which
    # records no graph): plain tensors there, the canvas copied into one
    with torch.inference_mode(False), torch.enable_grad():
        source = torch.zeros(*canvas.shape[:2], *size, dtype=canvas.dtype, device=canvas.device, requires_grad=True)
        resized = F.interpolate(source, size=canvas.shape[-2:], mode="bicubic", antialias=True, align_corners=False)
        (back,) = torch.autograd.grad(resized, source, canvas.clone())
    return back


POINT_ENOUGH = 2.0 / 255  # RMS of the fine detail point samples leave unexplained, under which they are taken


def _point_samples_explain(found: RelitResidual, n_images: int, height: int, width: int) -> bool:
    """Whether the relit original, point-sampled as it is, already explains every picture's fine detail
    (both high-passed as `picture_footprint` compares them) to within `POINT_ENOUGH`: a picture our
    renderer made, under the light the reading found, misses it by its 8-bit rounding and its mark alone.
    No area footprint can then explain much more, and the footprint search (a supersampled render and
    its blurs) is skipped. Looks at the picture and the original only."""
    from ..models.spread import local_mean

    if len(found.keep) == 0:
        return False
    pixel = found.fragments.pixel.index_select(0, found.keep)
    values = torch.cat([found.seen, found.expected], 1)
    detail = values - local_mean(values, pixel, (n_images, height, width), 1.5)
    misfit = ((detail[:, :3] - detail[:, 3:]) ** 2).mean(1)
    total = misfit.new_zeros(n_images).index_add_(0, found.image_index, misfit)
    count = misfit.new_zeros(n_images).index_add_(0, found.image_index, torch.ones_like(misfit))
    return bool(((total / count.clamp_min(1.0)).sqrt() < POINT_ENOUGH).all()) and bool((count > 0).all())


_CHOSEN: list = []  # (picture, its version, (sigma, resized)): the footprint one picture's reading chose


def chosen_before(image: torch.Tensor) -> tuple[float, float] | None:
    """The footprint (template sigma, resized factor; NaN: none) that reading the one picture `image`
    (1, 3, H, W) chose before, as long as the tensor is unchanged (a second look reads it again under
    other cameras; its sampling has not changed), or None."""
    return kept_with(image, _CHOSEN)


def as_choice(footprint: "Footprint | None") -> tuple[float, float]:
    """A one-picture footprint as `chosen_before` gives it back: (template sigma, resized factor), NaN
    for none (None: point samples)."""
    if footprint is None:
        return (float("nan"), float("nan"))
    resized = float("nan") if footprint.resized is None else float(footprint.resized[0])
    return (float(footprint.sigma[0]), resized)


def remember_choice(image: torch.Tensor, footprint: "Footprint") -> None:
    """Keep the footprint a reading of the one picture `image` chose, for `chosen_before`."""
    keep_with(image, _CHOSEN, as_choice(footprint))


def picture_footprint(mesh: MeshBatch, found: RelitResidual, cameras: Cameras, height: int, width: int,
                      sigmas: tuple[float, ...] = FOOTPRINT_SIGMAS,
                      resampled: tuple[float, ...] = RESAMPLED, known: tuple[float, float] | None = None,
                      shortcut: bool = True) -> Footprint:
    """Pick, per picture, the footprint (point samples, or the pixel area blurred by one of `sigmas`)
    under which the relit original best predicts the picture's fine detail: the largest normalised
    correlation between the picture and the prediction, both high-passed (their local mean over the
    object's pixels, sigma 1.5 px, taken off: a relighting misfit is slow and must not decide), over
    the pixels every candidate covers. The pixel's area is the mean of a rasterization `supersampling`
    times finer, shaded and summed per pixel without forming the finer image. Where a blurred footprint
    wins, the original rendered at another size and resized to the picture's (`resampled` factors,
    `resampled_prediction`) is tried too: a resized picture's bicubic filter is not a Gaussian, and
    the luminance of a texture's edges shows the difference. The choice looks at
    the picture and the original only, never at a key, so the matched filter's null stays the same.
    `known` (one picture: `chosen_before`): the footprint a reading of this picture chose before, the
    only one tried beside point samples and the pixel's area (point samples: taken at once). `shortcut`
    False: searched even where point samples explain the picture within POINT_ENOUGH (a prediction in
    linear light, whose levels that threshold does not measure)."""
    from ..imaging import blur_radius
    from ..models.spread import local_mean, within_reach
    from ..render import rasterize
    from ..render.blur import gaussian_blur  # compiled on the CPU, the same bits
    from ..render.rasterizer import whole_raster
    from ..render.supersample import box_mean_window, fused

    scale = supersampling(height, width)
    n_images = len(cameras)
    relit = found.relit
    forced = False
    if known is not None and n_images == 1:
        sigma, factor = known
        if math.isnan(sigma):  # read with point samples before: so again
            point = torch.full((1,), float("nan"), device=found.expected.device)
            return Footprint(found.expected, torch.ones_like(found.keep, dtype=torch.bool), point, None, None, scale)
        forced = not math.isnan(factor)
        sigmas, resampled = ((), (factor,)) if forced else ((sigma,), ())
    if shortcut and _point_samples_explain(found, n_images, height, width):  # nothing finer to find: no supersampled render
        point = torch.full((n_images,), float("nan"), device=found.expected.device)
        return Footprint(found.expected, torch.ones_like(found.keep, dtype=torch.bool), point, None, None, scale)
    positions = relit.positions.expand(n_images, -1, -1) if relit.positions.shape[0] == 1 else relit.positions
    clip = cameras.world_to_clip(positions, width / height)

    def finer(pix_to_face=None):
        """The rasterization `scale` times finer, and each fragment's picture pixel."""
        fine = rasterize(clip, relit.faces, height * scale, width * scale, pix_to_face)
        within = fine.pixel % (height * scale * width * scale)
        row = torch.div(within, width * scale, rounding_mode="floor")
        column = within - row * width * scale
        return fine, fine.batch * height * width + torch.div(row, scale, rounding_mode="floor") * width + column // scale

    # Hard edges: the sub-pixel mean is the antialiasing, and only wholly covered pixels are used.
    renderer = MeshRenderer()
    if fused(relit, renderer.shader):  # on the CPU one compiled pass, without forming the fragments
        sums, window, corner = box_mean_window(relit, cameras, found.lights, height, width, scale)
        sums, fine, parent = sums.to(found.expected.dtype), None, None
    else:
        fine, parent = finer()
        lit = renderer.shade(relit, cameras, found.lights, fine)
        sums = lit.new_zeros(n_images * height * width, 4).index_add_(0, parent, F.pad(lit, (0, 1), value=1.0)) / scale ** 2
    kept = found.fragments.pixel.index_select(0, found.keep)
    usable = sums[:, 3].index_select(0, kept) > 0.999
    widths = ((0.0,) if scale > 1 else ()) + tuple(sigmas)
    # Blurred at the picture's resolution, over the window the kept pixels and the widest blur reach.
    local, (_, rows, columns), (top, left) = within_reach(kept, (n_images, height, width), blur_radius(max(widths)))
    averaged = sums[:, :3].reshape(n_images, height, width, 3)[:, top: top + rows, left: left + columns]
    averaged = averaged.permute(0, 3, 1, 2)
    # each blur's values at the kept pixels, gathered plane by plane (P, 3)
    pick = lambda image: image.transpose(0, 1).reshape(3, -1).index_select(1, local).T  # noqa: E731
    candidates = [found.expected] + [pick(gaussian_blur(averaged, s)) for s in widths]
    pixel = kept[usable]
    image = found.image_index[usable]
    values = torch.cat([found.seen] + candidates, 1)[usable]  # (U, 3 + 3K): one masked blur for all
    detail = values - local_mean(values, pixel, (n_images, height, width), 1.5)
    seen, predicted = detail[:, :3].unsqueeze(1), detail[:, 3:].reshape(len(pixel), len(candidates), 3)
    agree = seen.new_zeros(n_images, len(candidates)).index_add_(0, image, (seen * predicted).sum(-1))
    power = seen.new_zeros(n_images, len(candidates)).index_add_(0, image, (predicted * predicted).sum(-1))
    scores = torch.nan_to_num(agree / power.sqrt(), nan=-float("inf"))
    choice = scores.argmax(1)  # (B,); a picture with nothing to compare keeps point samples
    template_sigmas = (float("nan"),) + widths
    resampled = tuple(f for f in resampled if max(height, width) / f <= RESAMPLED_LARGEST)
    # a blurred picture: was it resized from another size? (Not where no pixel is wholly covered: nothing
    # to compare, as under a second look's camera that shows the object at the frame's edge alone.)
    if resampled and len(pixel) > 0 and (forced or bool((choice > 0).any())):
        more = [pick_full(resampled_prediction(relit, cameras, found.lights, height, width, factor), kept)
                for factor in resampled]
        extra = torch.stack(more, 1)[usable]
        predicted = extra - local_mean(extra.reshape(len(pixel), -1), pixel, (n_images, height, width),
                                       1.5).reshape(extra.shape)
        agree = torch.cat([agree, seen.new_zeros(n_images, len(more)).index_add_(0, image, (seen * predicted).sum(-1))], 1)
        power = torch.cat([power, seen.new_zeros(n_images, len(more)).index_add_(0, image, (predicted * predicted).sum(-1))], 1)
        scores = torch.nan_to_num(agree / power.sqrt(), nan=-float("inf"))
        choice = scores.argmax(1)
        candidates = candidates + more
        template_sigmas = template_sigmas + (RESAMPLED_TEMPLATE_SIGMA,) * len(more)
    sigma = torch.tensor(template_sigmas, device=choice.device)[choice]
    factors = torch.tensor((float("nan"),) * (1 + len(widths)) + tuple(resampled), device=choice.device)
    resized = factors[choice] if len(template_sigmas) == len(factors) else torch.full_like(sigma, float("nan"))
    per_pixel = choice.index_select(0, found.image_index)
    expected = torch.stack(candidates).gather(0, per_pixel[None, :, None].expand(1, -1, 3))[0]
    usable = usable | (per_pixel == 0)  # point samples keep every interior pixel, as before
    if fine is None and bool((choice > 0).any()):  # the template under an area footprint needs the fragments
        fine, parent = finer(whole_raster(window, corner, height * scale, width * scale))
    return Footprint(expected, usable, sigma, fine, parent, scale, resized)


def linear_light_direction(expected: torch.Tensor) -> torch.Tensor:
    """How each predicted sRGB colour (P, 3) moves when white light is added to it in linear light ->
    directions (P, 3), the part orthogonal to the colour itself (its brightness is fitted on its own)
    of a unit vector.

    Every physically based engine shades in linear light: a specular highlight, Workbench's studio
    light or light bounced off the rest of the scene adds to the linear value. In sRGB that moves each
    channel by the slope of the sRGB curve at its linear value: steep on dark channels, so it lifts a
    saturated colour's darkest channel most (a deck chair's blue stripes) and is no longer white; on a
    grey pixel it is the brightness, and the direction returned is short there."""
    from ..imaging import srgb_to_linear

    linear = srgb_to_linear(expected)
    slope = torch.where(linear <= 0.0031308, torch.full_like(linear, 12.92),
                        1.055 / 2.4 * linear.clamp_min(0.0031308) ** (1.0 / 2.4 - 1.0))
    slope = F.normalize(slope, dim=1)
    brightness = F.normalize(expected, dim=1, eps=1e-6)
    return slope - (slope * brightness).sum(1, keepdim=True) * brightness


def take_off_linear_light(residual: torch.Tensor, expected: torch.Tensor, pixel: torch.Tensor,
                          shape: tuple[int, int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Residuals (P, 3) (brightness already taken off) with light added in linear light
    (`linear_light_direction`: a highlight, bounced light, a path tracer's noise) taken off where they
    vary along it more than across it, smoothly (fully at `LINEAR_LIGHT_RATIO`), over windows of
    `LINEAR_LIGHT_SIGMA` px; elsewhere the mark keeps all its colour. Returns the residuals and the
    direction taken off at each pixel, scaled by the square root of how much was (for the template's
    gain). Looks at the picture and the original only, never at a key."""
    from ..models.spread import local_mean

    added = linear_light_direction(expected)
    unit = F.normalize(added, dim=1, eps=1e-6)
    across = torch.cross(F.normalize(expected, dim=1, eps=1e-6), unit, dim=1)
    # both variances in one masked blur (each plane blurred as on its own)
    both = local_mean(torch.stack([(residual * unit).sum(1) ** 2, (residual * across).sum(1) ** 2], 1), pixel,
                      shape, LINEAR_LIGHT_SIGMA)
    along_added, along_across = both[:, 0].contiguous(), both[:, 1].contiguous()
    weight = (1.0 - LINEAR_LIGHT_RATIO * along_across / along_added.clamp_min(1e-12)).clamp(0.0, 1.0)
    weight = weight * ((added * added).sum(1) / LINEAR_LIGHT_DISTINCT ** 2).clamp(max=1.0)
    residual = residual - weight[:, None] * (residual * unit).sum(1, keepdim=True) * unit
    return residual, weight.sqrt()[:, None] * unit
