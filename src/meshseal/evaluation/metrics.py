"""What a person sees: the difference between renders of the original and the marked mesh, measured
over the object's pixels only (a background-dominated full frame hides a visible mark).

PSNR and SSIM (Gaussian 11x11, sigma 1.5, the usual constants) are averaged over the object's pixels;
FLIP is NVIDIA's perceptual difference for rendered pictures (`flip-evaluator`, default 67 pixels per
degree), averaged over the same pixels.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as F


def object_psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    """PSNR in dB of pictures (3, H, W) in [0, 1] over the pixels where `mask` (H, W) is true."""
    error = ((a - b) ** 2).mean(0)[mask]
    return 10.0 * math.log10(1.0 / max(float(error.mean()), 1e-12))


def _ssim_map(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM (H, W) of two pictures (3, H, W), averaged over channels."""
    coords = torch.arange(11, dtype=a.dtype) - 5
    gauss = torch.exp(-coords ** 2 / (2 * 1.5 ** 2))
    window = (gauss[:, None] * gauss[None, :] / gauss.sum() ** 2).expand(3, 1, 11, 11)
    blur = lambda x: F.conv2d(F.pad(x[None], (5, 5, 5, 5), mode="reflect"), window, groups=3)[0]  # noqa: E731
    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b, cov = blur(a * a) - mu_a ** 2, blur(b * b) - mu_b ** 2, blur(a * b) - mu_a * mu_b
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    return (((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2))).mean(0)


def object_ssim(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    """SSIM of pictures (3, H, W) averaged over the pixels where `mask` (H, W) is true."""
    return float(_ssim_map(a.float(), b.float())[mask].mean())


def object_flip(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    """Mean FLIP error of pictures (3, H, W) in [0, 1] (sRGB) over the pixels where `mask` is true."""
    import flip_evaluator

    as_array = lambda x: np.ascontiguousarray(x.detach().cpu().permute(1, 2, 0).numpy().astype(np.float32))  # noqa: E731
    error_map = flip_evaluator.evaluate(as_array(a), as_array(b), "LDR", applyMagma=False, computeMeanError=False)[0]
    return float(np.asarray(error_map).squeeze()[mask.cpu().numpy()].mean())


def visibility(original: torch.Tensor, marked: torch.Tensor, mask: torch.Tensor) -> dict:
    """Object-pixel PSNR, SSIM and FLIP of renders (B, 3, H, W) of the original and the marked mesh
    with the object's coverage `mask` (B, H, W), averaged over the B views; 8-bit quantised first, as
    saved pictures are. NaN where no view shows the object."""
    quantise = lambda x: torch.round(x.clamp(0, 1) * 255) / 255  # noqa: E731
    rows = [(object_psnr(quantise(o), quantise(m), k), object_ssim(quantise(o), quantise(m), k),
             object_flip(quantise(o), quantise(m), k)) for o, m, k in zip(original, marked, mask) if k.any()]
    if not rows:  # no view shows an interior pixel of the object (a thin or tiny one): nothing measured
        return {"psnr_object": math.nan, "ssim_object": math.nan, "flip_object": math.nan}
    return {"psnr_object": float(np.mean([r[0] for r in rows])), "ssim_object": float(np.mean([r[1] for r in rows])),
            "flip_object": float(np.mean([r[2] for r in rows]))}


def shown_texture_psnr(marked: torch.Tensor, original: torch.Tensor, used: torch.Tensor) -> torch.Tensor:
    """Texture PSNR (B,) over the texels each mesh shows: marked (B, 3, h, w) against original
    (B, 3, H, W) resampled alike, used (B, 1, H, W) (`batch_texels_used`) resized as the mark resized it."""
    from ..models.spread import resampled_like

    original = resampled_like(original, marked)
    used = F.interpolate(used.float(), size=marked.shape[-2:], mode="nearest")
    error = ((marked - original) ** 2).mean(1, keepdim=True)
    mse = (error * used).sum(dim=(1, 2, 3)) / used.sum(dim=(1, 2, 3)).clamp_min(1)
    return -10.0 * torch.log10(mse.clamp_min(1e-10))


MAX_FLIP = 0.03  # `meshseal embed`'s default visibility budget: the mark's mean FLIP over the object's pixels
BUDGET_VIEWS = 4  # ... in renders from this many seed views (`seed_renders`), as its report measures it
MIN_STRENGTH = 0.5  # a FLIP budget lowers the strength no further (the weakest mark docs/mark.md shows saved pictures reading at)
FLIP_ROUNDS = 4  # markings a FLIP budget tries at most


def strength_within(mark: Callable[[float], Any], flip: Callable[[Any], float], strength: float, max_flip: float
                    ) -> tuple[Any, float, float]:
    """The strength lowered from `strength` until the mark's FLIP is at most `max_flip`: `mark(s)` marks
    at strength s, `flip(marked)` measures it. Each step assumes FLIP grows as strength^0.7 (its power
    law near the default, docs/mark.md) and aims just under the budget, so one step usually suffices;
    at most `FLIP_ROUNDS` markings, never below `MIN_STRENGTH`. A FLIP of NaN (no view shows the object's
    interior, nothing to see) keeps the strength. Returns (marked, strength, FLIP)."""
    for round_ in range(FLIP_ROUNDS):
        marked = mark(strength)
        seen = flip(marked)
        if not seen > max_flip or strength <= MIN_STRENGTH or round_ == FLIP_ROUNDS - 1:  # NaN: nothing seen
            break
        strength = max(MIN_STRENGTH, strength * 0.98 * (max_flip / seen) ** (1 / 0.7))
    return marked, strength, seen


LOUDEST = "max"  # the strength asked as this word (`embed --strength max`): `strength_filled`'s
MIN_OBJECT_PSNR = 42.0  # `strength_filled`'s second budget: the marked renders' PSNR over the object (issue #45's floor)
MAX_STRENGTH = 4.0  # ... and its ceiling: texture PSNR about 28 dB over the shown texels, a mark plain in the texture itself
FILL_AIM = 0.97  # ... which aims each marking at this share of the FLIP budget (FLIP's growth is an estimate)
FILL_CLOSE = 1.05  # ... and stops once the next aim is within this factor of a strength already within both budgets


def strength_filled(mark: Callable[[float], Any], measure: Callable[[Any], dict], max_flip: float,
                    min_psnr: float = MIN_OBJECT_PSNR, start: float = 1.0, most: float = MAX_STRENGTH
                    ) -> tuple[Any, float, float, float]:
    """The loudest strength whose mark keeps both budgets of what a person sees: a mean FLIP over the
    object of at most `max_flip` and an object PSNR of at least `min_psnr` (`measure(marked)`: the
    `visibility` dict of the marked renders), the texture's own PSNR left to fall. `mark(s)` marks at
    strength s. From `start`, each marking aims just under the nearer budget's edge: FLIP grows as a
    power of the strength (0.7 near the default, docs/mark.md; from the second marking on, the power the
    last two measured), the object's error energy as its square (20 log10 of the strength in dB). At
    most `FLIP_ROUNDS` markings, between `MIN_STRENGTH` and `most`; where `start` is already over a
    budget the strength goes down as `strength_within` lowers it. A FLIP of NaN (no view shows the
    object's interior) keeps `start`. Returns (marked, strength, FLIP, object PSNR) of the loudest
    marking within both budgets, else of the last one tried (over a budget even at the floor)."""
    best = last = None
    strength, points = start, []
    for _ in range(FLIP_ROUNDS):
        marked = mark(strength)
        seen = measure(marked)
        flip, psnr = seen["flip_object"], seen["psnr_object"]
        last = (marked, strength, flip, psnr)
        if not flip == flip:  # NaN: nothing seen, no budget to fill
            return last
        within = flip <= max_flip and psnr >= min_psnr
        if within and (best is None or strength > best[1]):
            best = last
        points.append((math.log(strength), math.log(max(flip, 1e-9))))
        power = 0.7
        if len(points) >= 2 and abs(points[-1][0] - points[-2][0]) > 1e-6:
            power = min(max((points[-1][1] - points[-2][1]) / (points[-1][0] - points[-2][0]), 0.3), 1.5)
        aim = min(strength * (FILL_AIM * max_flip / max(flip, 1e-9)) ** (1 / power),
                  strength * 10 ** ((psnr - min_psnr - 0.05) / 20))
        aim = min(max(aim, MIN_STRENGTH), most)
        if best is not None and aim <= best[1] * FILL_CLOSE:  # no louder strength left to try
            break
        if best is None and strength <= MIN_STRENGTH:  # over a budget at the floor
            break
        strength = aim
    return best if best is not None else last


def seed_renders(mesh, views: int, size: int = 256):
    """A mesh (`Mesh`, brought into the canonical frame, or a `MeshBatch` already in it) rendered by our
    renderer from `views` seeded views (seed 0) -> pictures (B, 3, H, W) and the object's interior
    pixels (B, H, W): what `meshseal embed` reports visibility in."""
    from ..mesh import Mesh, normalize, to_z_up
    from ..render import MeshBatch, MeshRenderer
    from ..render.views import sample_views

    cameras, lights = sample_views(views, "seed", torch.Generator().manual_seed(0))
    batch = MeshBatch.from_mesh(normalize(to_z_up(mesh))) if isinstance(mesh, Mesh) else mesh
    device = batch.positions.device
    with torch.no_grad():
        out = MeshRenderer()(batch, cameras.to(device), lights.to(device), size, size)
    return out.image, out.rgba[..., 3] > 0.999


def render_pair(original, marked, views: int, size: int = 256):
    """`seed_renders` of both meshes -> pictures (B, 3, H, W) each and the object's interior pixels."""
    (image_a, inside), (image_b, _) = seed_renders(original, views, size), seed_renders(marked, views, size)
    return image_a, image_b, inside
