"""Splatting (Cole, Genova et al., "Differentiable Surface Rendering via Non-Differentiable Sampling").

Each foreground pixel's shaded colour is spread over its 3x3 neighbourhood with Gaussian weights
centred on its *splat position*: the surface point's screen position, whose value is the pixel centre
but whose gradient follows the vertices. This turns hard silhouettes into smooth functions of the
vertex positions and antialiases edges; interior pixels keep a total weight of exactly one.

Because every splat position equals its pixel centre in the forward pass, the Gaussian weights are
linearised around the centre: w_o(d) = g_o (1 + o.d / sigma^2) for a splat displaced by d. Value and
first derivative are exact at d = 0, and the whole splat becomes one 3x3 convolution. On the CPU (float32
and float64) the same linear map and its exact adjoint run as two fused numba kernels that skip the
background (alpha = 0) sources; elsewhere (CUDA, other dtypes) it is a torch conv2d.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
import torch.nn.functional as F
from torch.autograd.function import once_differentiable

from . import compiled
from .compiled import njit, prange


@functools.lru_cache(maxsize=16)
def _kernels(sigma: float, dtype, device) -> torch.Tensor:
    """(3, 3, 3): the normalised Gaussian g and its x- and y-moment kernels g*ox/sigma^2, g*oy/sigma^2,
    as correlation kernels (flipped offsets), indexed [kind, row, col]. Made once per sigma, dtype and
    device (every render asks for them): callers read them and never write."""
    with torch.inference_mode(False):  # kept for every later render: a plain tensor, even if made while detecting
        offsets = torch.tensor([-1.0, 0.0, 1.0], dtype=torch.float64)
        oy, ox = torch.meshgrid(offsets, offsets, indexing="ij")
        gauss = torch.exp(-(ox ** 2 + oy ** 2) / (2.0 * sigma * sigma))
        gauss = gauss / gauss.sum()
        # Scatter to offset o equals correlation at -o: flip the moment kernels' sign.
        return torch.stack([gauss, -gauss * ox / sigma ** 2, -gauss * oy / sigma ** 2]).to(dtype=dtype, device=device)


def _accumulate_conv(color: torch.Tensor, alpha: torch.Tensor, splat_xy: torch.Tensor,
                     sigma: float) -> torch.Tensor:
    """The splat's accumulation (B, H, W, C + 1) (premultiplied colour, coverage) as one conv2d."""
    n_batch, height, width, channels = color.shape
    rows = torch.arange(height, dtype=color.dtype, device=color.device).reshape(1, height, 1) + 0.5
    cols = torch.arange(width, dtype=color.dtype, device=color.device).reshape(1, 1, width) + 0.5
    dx = (splat_xy[..., 0] - cols).unsqueeze(1)  # (B, 1, H, W) displacement from the pixel centre
    dy = (splat_xy[..., 1] - rows).unsqueeze(1)
    values = torch.cat([color.permute(0, 3, 1, 2) * alpha.unsqueeze(1), alpha.unsqueeze(1)], dim=1)
    stacked = torch.cat([values, values * dx, values * dy], dim=1)  # (B, 3(C+1), H, W)
    kernels = _kernels(sigma, color.dtype, color.device)
    n = channels + 1
    weight = color.new_zeros(n, 3 * n, 3, 3)
    index = torch.arange(n, device=color.device)
    for kind in range(3):
        weight[index, kind * n + index] = kernels[kind]
    return F.conv2d(stacked, weight, padding=1).permute(0, 2, 3, 1)  # (B, H, W, C+1)


@njit(parallel=True, cache=True)
def _accumulate_forward(color, alpha, xy, gauss, inv_var, out):  # pragma: no cover - compiled
    """out[b, i, j] = sum over sources q = (i - oy, j - ox) with alpha != 0 of
    alpha(q) g_o (1 + (ox dx(q) + oy dy(q)) / sigma^2) * (color(q), 1); d(q) = xy(q) - centre(q).
    Each output row is written by one thread (gather over the 3 source rows)."""
    n_batch, height, width, channels = color.shape
    for line in prange(n_batch * height):
        b = line // height
        i = line - b * height
        out[b, i] = 0.0
        for oy in range(-1, 2):
            si = i - oy
            if si < 0 or si >= height:
                continue
            for sj in range(width):
                a = alpha[b, si, sj]
                if a == 0.0:
                    continue
                dx = xy[b, si, sj, 0] - (sj + 0.5)
                dy = xy[b, si, sj, 1] - (si + 0.5)
                for ox in range(-1, 2):
                    j = sj + ox
                    if j < 0 or j >= width:
                        continue
                    g = gauss[oy + 1, ox + 1]
                    w = (g + g * (ox * dx + oy * dy) * inv_var) * a
                    for c in range(channels):
                        out[b, i, j, c] += w * color[b, si, sj, c]
                    out[b, i, j, channels] += w


@njit(parallel=True, cache=True)
def _accumulate_backward(color, alpha, xy, gauss, inv_var, grad_out, every_alpha,
                         grad_color, grad_alpha, grad_xy):  # pragma: no cover - compiled
    """The adjoint of _accumulate_forward, per source pixel q over its 9 targets q + o. Sources with
    alpha = 0 get zero colour and position gradients; their alpha gradient only if `every_alpha`."""
    n_batch, height, width, channels = color.shape
    for line in prange(n_batch * height):
        b = line // height
        i = line - b * height
        for j in range(width):
            a = alpha[b, i, j]
            grad_xy[b, i, j, 0] = 0.0
            grad_xy[b, i, j, 1] = 0.0
            grad_alpha[b, i, j] = 0.0
            for c in range(channels):
                grad_color[b, i, j, c] = 0.0
            if a == 0.0 and not every_alpha:
                continue
            dx = xy[b, i, j, 0] - (j + 0.5)
            dy = xy[b, i, j, 1] - (i + 0.5)
            gdx = 0.0
            gdy = 0.0
            galpha = 0.0
            for oy in range(-1, 2):
                ti = i + oy
                if ti < 0 or ti >= height:
                    continue
                for ox in range(-1, 2):
                    tj = j + ox
                    if tj < 0 or tj >= width:
                        continue
                    g = gauss[oy + 1, ox + 1]
                    w = g + g * (ox * dx + oy * dy) * inv_var
                    dot = grad_out[b, ti, tj, channels]
                    for c in range(channels):
                        go = grad_out[b, ti, tj, c]
                        grad_color[b, i, j, c] += w * go
                        dot += color[b, i, j, c] * go
                    galpha += w * dot
                    gdx += g * ox * dot
                    gdy += g * oy * dot
            for c in range(channels):
                grad_color[b, i, j, c] *= a
            grad_alpha[b, i, j] = galpha
            grad_xy[b, i, j, 0] = gdx * inv_var * a
            grad_xy[b, i, j, 1] = gdy * inv_var * a


# A pixel whose total splat weight is within FULL of one is fully covered. Interior pixels sum to one
# only up to rounding; without the tolerance the branch (normalise vs. blend with the background), and
# with it the gradient, would flip with the summation order.
FULL = 1e-4


@njit(parallel=True, cache=True)
def _composite_forward(accumulated, background, image, coverage):  # pragma: no cover - compiled
    """Fully covered (cov >= 1 - FULL): image = acc[:C] / cov, coverage 1.
    Otherwise: image = acc[:C] + (1 - cov) * background[b], coverage cov."""
    n_batch, height, width, channels = image.shape
    for line in prange(n_batch * height):
        b = line // height
        i = line - b * height
        for j in range(width):
            cov = accumulated[b, i, j, channels]
            if cov >= 1.0 - FULL:
                for c in range(channels):
                    image[b, i, j, c] = accumulated[b, i, j, c] / cov
                coverage[b, i, j] = 1.0
            else:
                for c in range(channels):
                    image[b, i, j, c] = accumulated[b, i, j, c] + (1.0 - cov) * background[b, c]
                coverage[b, i, j] = cov


@njit(parallel=True, cache=True)
def _composite_backward(accumulated, background, grad_image, grad_coverage, grad_accumulated):  # pragma: no cover
    """Adjoint of _composite_forward w.r.t. acc."""
    n_batch, height, width, channels = grad_image.shape
    for line in prange(n_batch * height):
        b = line // height
        i = line - b * height
        for j in range(width):
            cov = accumulated[b, i, j, channels]
            grad_cov = 0.0
            if cov >= 1.0 - FULL:
                for c in range(channels):
                    g = grad_image[b, i, j, c]
                    grad_accumulated[b, i, j, c] = g / cov
                    grad_cov -= g * accumulated[b, i, j, c] / (cov * cov)
            else:
                for c in range(channels):
                    g = grad_image[b, i, j, c]
                    grad_accumulated[b, i, j, c] = g
                    grad_cov -= g * background[b, c]
                grad_cov += grad_coverage[b, i, j]
            grad_accumulated[b, i, j, channels] = grad_cov


def _forward_torch(color, alpha, xy, gauss, inv_var, background):
    """`_accumulate_forward` then `_composite_forward` in torch, for a process that has not loaded
    the compiled kernels (`compiled.spare`): the same arithmetic in the same order, so the same bits.
    Each target pixel adds its nine sources as the kernel meets them (source rows below, at and
    above it; in each, the source columns from left to right), each term in float64 and the sum
    rounded to the arrays' type after each, as the kernel's `+=` on the arrays does; only over the
    box that sources of non-zero alpha reach (elsewhere the sums are 0). numpy in and out:
    (accumulated, image, coverage)."""
    c, a, xy = (torch.from_numpy(x) for x in (color, alpha, xy))
    n_batch, height, width, channels = c.shape
    total = c.new_zeros(n_batch, height, width, channels + 1)
    rows, cols = (a != 0).any(0).any(1).nonzero()[:, 0], (a != 0).any(0).any(0).nonzero()[:, 0]
    if len(rows):
        top, bottom = max(int(rows[0]) - 1, 0), min(int(rows[-1]) + 2, height)
        left, right = max(int(cols[0]) - 1, 0), min(int(cols[-1]) + 2, width)
        box = (slice(None), slice(top, bottom), slice(left, right))
        box_h, box_w = bottom - top, right - left
        centre_y = torch.arange(top, bottom, dtype=torch.float64).reshape(1, box_h, 1) + 0.5
        centre_x = torch.arange(left, right, dtype=torch.float64).reshape(1, 1, box_w) + 0.5
        dx, dy = xy[box][..., 0].double() - centre_x, xy[box][..., 1].double() - centre_y  # float32 - float64, as there
        values = torch.cat([c[box], torch.ones_like(a[box])[..., None]], -1).double()  # times each source's weight
        pad = lambda x: torch.nn.functional.pad(x, (1, 1, 1, 1))  # noqa: E731  sources off the box: alpha 0
        source_alpha, source_dx, source_dy = pad(a[box]), pad(dx), pad(dy)
        source_values = torch.nn.functional.pad(values, (0, 0, 1, 1, 1, 1))
        sums = total[box]
        g, inv = torch.from_numpy(gauss).double(), float(inv_var)
        for oy in (-1, 0, 1):
            for ox in (1, 0, -1):  # the source column j - ox, from left to right
                at = (slice(None), slice(1 - oy, 1 - oy + box_h), slice(1 - ox, 1 - ox + box_w))
                weight = g[oy + 1, ox + 1]
                weight = (weight + weight * (ox * source_dx[at] + oy * source_dy[at]) * inv) * source_alpha[at].double()
                added = (sums.double() + weight[..., None] * source_values[at]).to(sums.dtype)
                sums = torch.where((source_alpha[at] != 0.0)[..., None], added, sums)
        total[box] = sums
    coverage = total[..., channels]
    full = (coverage.double() >= 1.0 - FULL)[..., None]
    covered = total[..., :channels] / coverage[..., None]
    blended = (total[..., :channels].double()
               + (1.0 - coverage.double())[..., None] * torch.from_numpy(background).double()[:, None, None, :])
    image = torch.where(full, covered, blended.to(c.dtype))
    return total.numpy(), image.numpy(), torch.where(full[..., 0], torch.ones_like(coverage), coverage).numpy()


def _numpy(tensor: torch.Tensor, dtype) -> np.ndarray:
    return tensor.detach().to(dtype).contiguous().numpy()


class _SplatCPU(torch.autograd.Function):
    """The whole splat on the CPU (numba): accumulation and compositing, with the exact adjoint
    (first order only). background is (B, C)."""

    @staticmethod
    def forward(ctx, color, alpha, splat_xy, background, sigma):
        dtype = color.dtype
        c, a, xy = _numpy(color, dtype), _numpy(alpha, dtype), _numpy(splat_xy, dtype)
        bg = _numpy(background, dtype)
        n_batch, height, width, channels = c.shape
        gauss = _kernels(sigma, dtype, "cpu")[0].numpy()
        inv_var = c.dtype.type(1.0 / (sigma * sigma))
        if compiled.spare(n_batch * height * width):  # a small job while the kernels are not loaded
            with compiled.in_torch():
                accumulated, image, coverage = _forward_torch(c, a, xy, gauss, inv_var, bg)
        else:
            accumulated = np.empty((n_batch, height, width, channels + 1), dtype=c.dtype)
            _accumulate_forward(c, a, xy, gauss, inv_var, accumulated)
            image = np.empty_like(c)
            coverage = np.empty_like(a)
            _composite_forward(accumulated, bg, image, coverage)
        ctx.save_for_backward(color, alpha, splat_xy, background)
        ctx.sigma, ctx.accumulated = sigma, accumulated  # a private array: no reference to the outputs
        return torch.from_numpy(image), torch.from_numpy(coverage)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_image, grad_coverage):
        color, alpha, splat_xy, background = ctx.saved_tensors
        dtype, sigma, accumulated = color.dtype, ctx.sigma, ctx.accumulated
        c, a, xy = _numpy(color, dtype), _numpy(alpha, dtype), _numpy(splat_xy, dtype)
        if grad_image is None:
            grad_image = color.new_zeros(color.shape)
        if grad_coverage is None:
            grad_coverage = alpha.new_zeros(alpha.shape)
        grad_image_np = _numpy(grad_image, dtype)
        grad_accumulated = np.empty_like(accumulated)
        _composite_backward(accumulated, _numpy(background, dtype), grad_image_np, _numpy(grad_coverage, dtype),
                            grad_accumulated)
        gauss = _kernels(sigma, dtype, "cpu")[0].numpy()
        grad_color, grad_alpha, grad_xy = np.empty_like(c), np.empty_like(a), np.empty_like(xy)
        _accumulate_backward(c, a, xy, gauss, c.dtype.type(1.0 / (sigma * sigma)), grad_accumulated,
                             bool(ctx.needs_input_grad[1]), grad_color, grad_alpha, grad_xy)
        grad_background = None
        if ctx.needs_input_grad[3]:
            coverage = torch.from_numpy(accumulated[..., -1:])
            uncovered = torch.where(coverage >= 1.0 - FULL, 0.0, 1.0 - coverage)
            grad_background = (torch.from_numpy(grad_image_np) * uncovered).sum((1, 2)).to(background.dtype)
        return (torch.from_numpy(grad_color), torch.from_numpy(grad_alpha).to(alpha.dtype),
                torch.from_numpy(grad_xy).to(splat_xy.dtype), grad_background, None)


def splat(color: torch.Tensor, alpha: torch.Tensor, splat_xy: torch.Tensor, background: torch.Tensor,
          sigma: float = 0.5) -> tuple[torch.Tensor, torch.Tensor]:
    """Splat colours (B, H, W, C) with coverage alpha (B, H, W) at positions (B, H, W, 2) in pixels.

    splat_xy must lie at (or within a small fraction of a pixel of) the pixel centres (j + 0.5, i + 0.5).
    Returns the composited image (B, H, W, C) over `background` (C,) or (B, C) and the coverage (B, H, W).
    """
    n_batch, channels = color.shape[0], color.shape[-1]
    background = background.to(color.dtype).reshape(-1, channels)
    if color.device.type == "cpu" and color.dtype in (torch.float32, torch.float64):
        return _SplatCPU.apply(color, alpha, splat_xy, background.expand(n_batch, channels), sigma)
    accumulated = _accumulate_conv(color, alpha, splat_xy, sigma)
    coverage = accumulated[..., -1:]
    full = coverage >= 1.0 - FULL
    normalised = accumulated[..., :-1] / torch.where(full, coverage, torch.ones_like(coverage))
    blended = accumulated[..., :-1] + (1.0 - coverage) * background.reshape(-1, 1, 1, channels)
    image = torch.where(full, normalised, blended)
    return image, torch.where(full, torch.ones_like(coverage), coverage).squeeze(-1)
