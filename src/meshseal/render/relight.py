"""Estimate a picture's lighting from the mesh it shows, so the original can be rendered as it would
look in that picture (informed detection subtracts it to isolate the watermark)."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .cameras import fibonacci_directions
from .lighting import ATTENUATION, K_AMBIENT, K_DIFFUSE, PointLights

LIGHT_DISTANCES = (2.0, 3.0, 4.5, 7.0, 12.0)


def fit_point_light(seen: torch.Tensor, albedo: torch.Tensor, position: torch.Tensor, normal: torch.Tensor,
                    image_index: torch.Tensor, n_images: int, directions: int = 96, max_pixels: int = 512):
    """Explain observed colours (P, 3) as albedo (P, 3) under an ambient term plus one point light (our
    Phong model, attenuation included), per image of `image_index` (P,).

    The light's position is the best of `directions` x LIGHT_DISTANCES around the origin; for each,
    the per-channel ambient and light strengths are a closed-form least-squares fit. `position`,
    `normal` (P, 3): surface points and normals facing the camera. Returns the shader's parameters:
    ambient factor (n_images, 3) for the materials' Ka, and PointLights (one light per image). Images
    with too few pixels get a plain ambient light.
    """
    with torch.no_grad():
        seen, albedo = seen.detach(), albedo.detach()
        unit = fibonacci_directions(directions).to(seen)
        grid = torch.cat([unit * d for d in LIGHT_DISTANCES])  # (K, 3)
        ring = fibonacci_directions(32).to(seen)
        ambient = seen.new_ones(n_images, 3) / K_AMBIENT
        light_position = seen.new_zeros(n_images, 1, 3)
        intensity = seen.new_zeros(n_images, 1, 3)
        fits = []  # (image, its pixels (y, u, p, n), the best of the grid) of each image with enough pixels
        for index in range(n_images):
            chosen = torch.nonzero(image_index == index).squeeze(1)
            if len(chosen) < 16:
                continue
            chosen = chosen[:: max(1, len(chosen) // max_pixels)]  # an even subsample is plenty for 7 numbers
            pixels = tuple(values.index_select(0, chosen) for values in (seen, albedo, position, normal))
            fits.append((index, pixels, _best_light(*pixels, grid)))  # the grid image by image: (P, K) in the cache
        if len(fits) == 1:
            index, pixels, best = fits[0]
            for step in (0.3, 0.1, 0.03):  # then search ever closer around the best
                centre = best[2]
                best = min(best, _best_light(*pixels, centre + step * centre.norm() * ring), key=lambda b: b[0])
            fits[0] = (index, pixels, best)
        elif fits:  # many images (a registration scores a hundred views): their searches around the best at once
            size = max(len(pixels[0]) for _, pixels, _ in fits)
            stacked = [torch.stack([F.pad(pixels[k], (0, 0, 0, size - len(pixels[k]))) for _, pixels, _ in fits])
                       for k in range(4)]  # (F, P, 3), padded with zeros, which add nothing to the sums
            best = [torch.stack([torch.as_tensor(fit[2][k], dtype=seen.dtype) for fit in fits]) for k in range(4)]
            for step in (0.3, 0.1, 0.03):
                centre = best[2]
                closer = _best_light(*stacked, centre[:, None] + step * centre.norm(dim=-1)[:, None, None] * ring)
                better = closer[0] < best[0]  # a tie keeps the first, as `min` does
                best = [torch.where(better.reshape(-1, *[1] * (new.dim() - 1)), new, old) for new, old in zip(closer, best)]
            fits = [(index, pixels, tuple(part[i] for part in best)) for i, (index, pixels, _) in enumerate(fits)]
        for index, _, (_, a, centre, d) in fits:
            ambient[index], light_position[index, 0], intensity[index, 0] = a / K_AMBIENT, centre, d / K_DIFFUSE
        return ambient, PointLights(light_position, intensity)


def _best_light(y, u, position, normal, candidates):
    """Least-squares fit of y ~ a * u + d * u * lambert(candidate) per channel for each candidate light
    position (K, 3); returns (residual, a (3,), position (3,), d (3,)) of the best one. Every sum over
    pixels is a (P, K) matrix product: every candidate is scored at once, not in a loop. Batched: pixels
    (F, P, 3) and candidates (F, K, 3), each image its own, return (F,), (F, 3), (F, 3), (F, 3)."""
    kc, kl, kq = ATTENUATION
    # The (P, K) terms are built in place, in the same order of operations as the plain expressions
    # (squared = |c|^2 - 2 p.c + |p|^2, lit = max(n.c - n.p, 0) / distance / (kc + kl distance + kq
    # squared)): the same bits, without ten (P, K) temporaries.
    across = candidates.transpose(-1, -2)  # (3, K) or (F, 3, K)
    squared = (position @ across).mul_(-2.0).add_((candidates * candidates).sum(-1).unsqueeze(-2))
    squared.add_((position * position).sum(-1, True))
    distance = squared.clamp_min(1e-12).sqrt_()  # (P, K)
    lit = (normal @ across).sub_((normal * position).sum(-1, True)).div_(distance).clamp_min_(0.0)
    lit.div_(distance.mul_(kl).add_(kc).add_(squared.mul_(kq)))  # (P, K); distance and squared used up
    uu, uy = u * u, u * y
    suu, suy = uu.sum(-2).unsqueeze(-1), uy.sum(-2).unsqueeze(-1)  # (3, 1)
    suv, svy = uu.transpose(-1, -2) @ lit, uy.transpose(-1, -2) @ lit  # (3, K)
    svv = uu.transpose(-1, -2) @ lit.mul_(lit)
    det = (suu * svv - suv * suv).clamp_min(1e-9)
    a = ((svv * suy - suv * svy) / det).clamp_min(0.0)
    d = ((suu * svy - suv * suy) / det).clamp_min(0.0)
    residual = ((y * y).sum(-2).unsqueeze(-1) - 2 * (a * suy + d * svy) + a * a * suu + 2 * a * d * suv
                + d * d * svv).sum(-2)  # (K,) or (F, K)
    if residual.dim() == 1:
        best = int(residual.argmin())
        return float(residual[best]), a[:, best], candidates[best], d[:, best]
    best = residual.argmin(-1)  # (F,)
    rows = torch.arange(len(best), device=best.device)
    return residual[rows, best], a[rows, :, best], candidates[rows, best], d[rows, :, best]


def relight_fragments(batch, fragments, cameras, seen: torch.Tensor, albedo: torch.Tensor | None = None,
                      fit_on: torch.Tensor | None = None, directions: int = 96, max_pixels: int = 512,
                      predict: bool = True, points: tuple | None = None):
    """Fit a point light to the observed colours `seen` (P, 3) at `fragments` of `batch` (a MeshBatch
    with uvs) seen from `cameras`; returns the colours our shader predicts there (P, 3), differentiable
    w.r.t. the camera through the texture lookup (the light is held fixed), and the fit itself
    (ambient factors (B, 3), PointLights). `albedo` (P, 3) replaces the texture looked up at the pixel
    centres (e.g. an antialiased unlit render, to match an antialiased picture); `fit_on` (P,) bool
    limits the fit to some pixels (the prediction covers all); `directions` and `max_pixels` are
    `fit_point_light`'s (a coarser, cheaper fit where only a ranking needs it); `predict` False skips
    the prediction (None in its place) where only the fit is wanted. `points`: `unrender.surface_points`
    of these fragments, where the caller has them."""
    from .shader import PhongShader
    from .unrender import surface_attributes, surface_points

    n_images = fragments.shape[0]
    if albedo is None:
        _, albedo = surface_attributes(batch, fragments)
    if points is not None:
        position, normal = points
    else:
        with torch.no_grad():
            position, normal = surface_points(batch, fragments, cameras)
    used = slice(None) if fit_on is None else fit_on
    ambient, lights = fit_point_light(seen[used], albedo[used], position[used], normal[used], fragments.batch[used],
                                      n_images, directions, max_pixels)
    if not predict:
        return None, ambient, lights
    pick = lambda table: table.index_select(0, fragments.batch)  # noqa: E731
    eye = cameras.eye.to(position).detach()
    predicted = PhongShader()(position, normal, albedo, pick(eye), pick(lights.position), pick(lights.intensity),
                              pick(ambient), torch.zeros_like(albedo), albedo.new_full((len(albedo),), 32.0))
    return predicted.clamp(0.0, 1.0), ambient, lights
