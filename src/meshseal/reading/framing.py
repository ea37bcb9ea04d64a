"""Put the object in a canonical frame before decoding, in training and in detection alike.

The decoder always sees the object's bounding box (plus a margin) as a square `size` x `size` picture,
so a screenshot where the object fills 20 % or 100 % of the frame, at any resolution, looks like the
renders it was trained on.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
import torch.nn.functional as F

BOX_MARGIN = 0.08  # each side of a framed box leaves this fraction of the object's extent around it


def boxes_from_mask(mask: torch.Tensor, margin: float = BOX_MARGIN) -> torch.Tensor:
    """(B, H, W) mask -> square boxes (B, 4) as (centre_x, centre_y, half_side) in pixels.

    An empty mask gives the whole image.
    """
    n, height, width = mask.shape
    rows, cols = mask.any(dim=2), mask.any(dim=1)  # one pass on the mask's device, no per-image round trip
    row_index = torch.arange(height, device=mask.device)
    col_index = torch.arange(width, device=mask.device)
    top = torch.where(rows, row_index, height).amin(1)
    bottom = torch.where(rows, row_index, -1).amax(1) + 1
    left = torch.where(cols, col_index, width).amin(1)
    right = torch.where(cols, col_index, -1).amax(1) + 1
    top, bottom, left, right = (t.double().cpu() for t in (top, bottom, left, right))
    half = (torch.maximum(bottom - top, right - left) / 2 * (1 + 2 * margin)).clamp_min(4.0)
    boxes = torch.stack([(left + right) / 2, (top + bottom) / 2, half], dim=1)
    empty = ~rows.any(dim=1).cpu()
    boxes[empty] = torch.tensor([width / 2, height / 2, max(height, width) / 2], dtype=boxes.dtype)
    return boxes.float()


def box_from_points(xy: torch.Tensor, height: int, width: int, margin: float = BOX_MARGIN) -> torch.Tensor:
    """The square box (1, 3) of pixel positions xy (N, 2) (e.g. projected vertices), as `boxes_from_mask`
    would find it for the pixels they cover, clipped to the picture."""
    xy = xy.detach().float().cpu().clamp(torch.zeros(2), torch.tensor([float(width), float(height)]))
    (left, top), (right, bottom) = xy.amin(0).tolist(), xy.amax(0).tolist()
    return _square_box(top, bottom, left, right, margin).unsqueeze(0)


def _square_box(top: float, bottom: float, left: float, right: float, margin: float) -> torch.Tensor:
    half = max(bottom - top, right - left) / 2 * (1 + 2 * margin)
    return torch.tensor([(left + right) / 2, (top + bottom) / 2, max(half, 4.0)])


def crop_boxes(image: torch.Tensor, boxes: torch.Tensor, size: int, background: torch.Tensor | None = None) -> torch.Tensor:
    """Crop square boxes (B, 3) from images (B, C, H, W) and resample to (B, C, size, size), bilinear,
    with antialiasing when shrinking, each picture by its own box's factor (a batch frames every
    picture as it would be framed alone). Outside the image is `background` (B, C) (default 0)."""
    n, channels, height, width = image.shape
    boxes = boxes.to(image.device, image.dtype)
    if background is None:
        background = image.new_zeros(n, channels)
    shrinks = 2 * boxes[:, 2] / size
    if n > 1 and bool((shrinks > 1.5).any()) and bool((shrinks != shrinks[0]).any()):
        return torch.cat([crop_boxes(image[i:i + 1], boxes[i:i + 1], size, background[i:i + 1]) for i in range(n)])
    shift = background.reshape(n, channels, 1, 1)
    shrink = float((2 * boxes[:, 2]).max()) / size
    source = image - shift
    if shrink > 1.5:  # prefilter so bilinear resampling does not alias
        factor = 1.0 / shrink
        source = F.interpolate(source, scale_factor=factor, mode="bilinear", align_corners=False, antialias=True)
    theta = image.new_zeros(n, 2, 3)
    theta[:, 0, 0] = boxes[:, 2] / (width / 2)
    theta[:, 1, 1] = boxes[:, 2] / (height / 2)
    theta[:, 0, 2] = boxes[:, 0] / (width / 2) - 1
    theta[:, 1, 2] = boxes[:, 1] / (height / 2) - 1
    grid = F.affine_grid(theta, (n, channels, size, size), align_corners=False)
    return F.grid_sample(source, grid, mode="bilinear", padding_mode="zeros", align_corners=False) + shift


def border_pixels(image: np.ndarray) -> np.ndarray:
    """The pixels of the image's (H, W, C) outermost rows and columns (N, C)."""
    return np.concatenate([image[0], image[-1], image[:, 0], image[:, -1]])


def estimate_background(image: np.ndarray) -> np.ndarray:
    """The median colour of the image border (H, W, 3) -> (3,)."""
    return np.median(border_pixels(image), axis=0)


@functools.lru_cache(maxsize=4)
def _plane_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`background_plane`'s pixel rows and columns (H, W), its design matrix over the whole picture
    (H, W, 3) and the border (H, W) bool, for pictures of one size (read-only: shared between calls)."""
    ys, xs = np.mgrid[0:height, 0:width]
    whole = np.stack([np.ones_like(xs, dtype=np.float64), xs / width, ys / height], -1)
    border = np.zeros((height, width), dtype=bool)
    border[0], border[-1], border[:, 0], border[:, -1] = True, True, True, True
    for array in (ys, xs, whole, border):
        array.flags.writeable = False
    return ys, xs, whole, border


def _opening(mask: np.ndarray) -> np.ndarray:
    """`scipy.ndimage.binary_opening(mask, iterations=1)` of a 2-D mask (the cross-shaped structure,
    nothing outside the picture), by shifts: the same pixels, without scipy's general machinery."""
    if mask.ndim != 2 or min(mask.shape) < 3:
        from scipy import ndimage

        return ndimage.binary_opening(mask, iterations=1)
    eroded = mask.copy()
    eroded[1:] &= mask[:-1]
    eroded[:-1] &= mask[1:]
    eroded[:, 1:] &= mask[:, :-1]
    eroded[:, :-1] &= mask[:, 1:]
    eroded[0], eroded[-1], eroded[:, 0], eroded[:, -1] = False, False, False, False
    opened = eroded.copy()
    opened[1:] |= eroded[:-1]
    opened[:-1] |= eroded[1:]
    opened[:, 1:] |= eroded[:, :-1]
    opened[:, :-1] |= eroded[:, 1:]
    return opened


START_SPREAD = 4.0  # `background_plane` starts from the border pixels within this many thresholds of its median colour ...
START_SHARE = 0.25  # ... where at least this share of the border is


def background_plane(image: np.ndarray, threshold: float = 0.03, rounds: int = 3) -> np.ndarray:
    """The picture's background (H, W, 3) as a linear ramp per channel (a plain colour is the flat
    case) fitted to the border by least squares; border pixels more than `threshold` off the fit (the
    object touching the frame) are dropped and the fit repeated. The first fit takes only the border
    pixels within START_SPREAD thresholds of the border's median colour (all of them where that leaves
    under START_SHARE): an object touching the frame along a tenth of the border, darker than the
    background, would otherwise pull a fit of every pixel off the background everywhere, leave no
    pixel within the threshold and the picture all object."""
    height, width = image.shape[:2]
    ys, xs, whole, border = _plane_grid(height, width)
    design = lambda y, x: np.stack([np.ones_like(x, dtype=np.float64), x / width, y / height], -1)  # noqa: E731
    rows, columns = ys[border], xs[border]
    values = image[border].astype(np.float64)
    keep = np.abs(values - np.median(values, axis=0)).max(-1) <= START_SPREAD * threshold
    if keep.mean() < START_SHARE:
        keep = np.ones(len(values), dtype=bool)
    for _ in range(rounds):
        coefficients, *_ = np.linalg.lstsq(design(rows[keep], columns[keep]), values[keep], rcond=None)
        off = np.abs(design(rows, columns) @ coefficients - values).max(-1) > threshold
        if off.all() or (~off == keep).all():
            break
        keep = ~off
    return (whole @ coefficients).astype(image.dtype)


def object_mask(image: np.ndarray, threshold: float = 0.03, trim: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Find the object in a picture with a plain or smoothly graded background: (H, W, 3) float ->
    mask (H, W), background (3,) (the border's median colour).

    Pixels that differ from the background (`background_plane`) by more than `threshold`, cleaned up
    by keeping the largest connected components that together hold 99 % of the area, then trimmed to
    the pixels the object covers at least half (`half_covered`), as a renderer's hard raster marks
    them: the antialiased rim that any difference picks up would make silhouettes half a pixel too wide,
    which registration would then match (experiments/registration_conditions.py, docs/reading.md). `trim`
    False skips that last step (a reader that only counts the object's pixels).
    """
    from scipy import ndimage

    background = estimate_background(image)
    plane = background_plane(image, threshold)
    off = np.abs(image - plane)
    mask = functools.reduce(np.maximum, np.moveaxis(off, -1, 0)) > threshold  # .max(-1), channel by channel: faster
    mask = _opening(mask)
    labels, count = ndimage.label(mask)
    if count > 1:
        sizes = ndimage.sum(mask, labels, index=np.arange(1, count + 1))
        order = np.argsort(sizes)[::-1]
        cumulative = np.cumsum(sizes[order]) / sizes.sum()
        keep = order[: int(np.searchsorted(cumulative, 0.99)) + 1] + 1
        mask = np.isin(labels, keep)
    return (half_covered(image - plane, mask) if trim else mask), background


def inner_picture(image: np.ndarray, threshold: float = 0.03, fill: float = 0.97) -> tuple[int, int, int, int] | None:
    """Where a picture holds another picture (a render pasted into a screenshot of a viewer window, a
    page, a collage): the inner picture's rows and columns (top, bottom, left, right), or None.

    The plain-background object of `image` (H, W, 3) is then a filled axis-aligned rectangle (at least
    `fill` of its box, smaller than the picture, at least 32 px a side) whose own border is one plain
    colour (nine tenths of it within `threshold` of its median) with an object inside. Reading the
    inner picture alone gives registration the frame the picture was made in, and the object its own
    background."""
    from scipy import ndimage

    mask, _ = object_mask(image, threshold, trim=False)
    labels, count = ndimage.label(mask)
    if count == 0:
        return None
    sizes = ndimage.sum(mask, labels, index=np.arange(1, count + 1))
    rows, cols = ndimage.find_objects(labels)[int(np.argmax(sizes))]
    top, bottom, left, right = rows.start, rows.stop, cols.start, cols.stop
    height, width = image.shape[:2]
    if (bottom - top < 32 or right - left < 32 or (bottom - top >= height - 2 and right - left >= width - 2)
            or sizes.max() < fill * (bottom - top) * (right - left)):
        return None
    inner = image[top:bottom, left:right]
    edge = border_pixels(inner)
    if np.mean(np.abs(edge - np.median(edge, axis=0)).max(-1) <= threshold) < 0.9:
        return None
    found, _ = object_mask(inner, threshold, trim=False)
    if found.sum() < 16 or found.mean() > 0.9:
        return None
    return top, bottom, left, right


def half_covered(difference: np.ndarray, mask: np.ndarray, sigma: float = 1.5, min_contrast: float = 0.1) -> np.ndarray:
    """`mask` (H, W) of the pixels that differ from the background, trimmed on its one-pixel rim to
    those the object covers at least half. `difference` (H, W, 3): the picture minus its background.
    An antialiased rim pixel is a blend, background + coverage x (object - background); the object's
    colour there is taken from the mask's core nearby (a Gaussian mean over the core, `sigma` pixels)
    and the coverage is the rim pixel's projection on it. Rim pixels with no core near, or whose object
    colour is within `min_contrast` of the background, stay as they are."""
    from scipy import ndimage

    core = ndimage.binary_erosion(mask, iterations=1)
    rim = mask & ~core
    near = ndimage.gaussian_filter(core.astype(np.float32), sigma)
    colour = np.stack([ndimage.gaussian_filter(difference[..., k] * core, sigma) for k in range(difference.shape[-1])], -1)
    colour = colour / np.maximum(near, 1e-6)[..., None]
    contrast = (colour * colour).sum(-1)
    coverage = (difference * colour).sum(-1) / np.maximum(contrast, 1e-12)
    judged = rim & (near > 0.05) & (contrast > min_contrast ** 2)
    trimmed = mask.copy()
    trimmed[judged] = coverage[judged] >= 0.5
    return trimmed


def frame(image: torch.Tensor, alpha: torch.Tensor, size: int, background: torch.Tensor) -> torch.Tensor:
    """Crop the object's bounding box (from the coverage) into a square size x size picture."""
    boxes = boxes_from_mask(alpha.detach().cpu() > 0.5)
    return crop_boxes(image, boxes, size, background.to(image))
