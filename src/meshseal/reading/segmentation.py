"""Find a known object in a picture whose background is busy (a photograph, a game scene, a textured
backdrop), where "pixels that differ from the border's colour" (`framing.object_mask`) marks everything.

Informed detection has the original mesh, so it knows the object's colours: renders of the original
from all around give a colour histogram of the object, the picture's own pixels one of the picture, and
their ratio per pixel (histogram back-projection, smoothed over a few pixels) says where the object
probably is. That guess seeds GrabCut (OpenCV), which fits colour mixtures to the picture itself and
cuts along its edges. Registration then runs on the mask as on a plain background's
(`registration.register_with_masks` decides between this guess and the plain-background one). Where neither
registers, the silhouette of the best camera found seeds a second cut (`recut`): even a camera several
pixels off, or a wrong view of a like shape, says where the object is far better than colours alone.
The same second cut mends a plain background's mask where a dark object on a dark backdrop lost parts.
"""

from __future__ import annotations

import numpy as np
import torch

PLAIN_SHARE = 0.99  # a background is plain (or a smooth ramp) when the ramp fit explains this share of the border
PLAIN_FIRST = 0.8  # ... and where it explains at least this share (an object the frame cuts off), the plain guess is registered first
GUESSES_AGREE = 0.95  # a guided cut whose IoU with the plain-background mask is at least this adds nothing
BINS = 16  # colour histogram bins per channel
CUT_SIZE = 384  # GrabCut runs on a copy whose longer side is at most this many pixels
COLOUR_VIEWS = 16  # views of the original whose pixels make its colour histogram
KEEP_AREA = 0.9  # the largest connected parts of a cut holding this share of its area are kept
RECUT_BAND = 8  # pixels around a registered silhouette that `recut` may add (in a 256-pixel picture; scaled with its size)


def plain_share(image: np.ndarray, threshold: float = 0.03) -> float:
    """The share of the picture's (H, W, 3, in [0, 1]) border within `threshold` of the linear ramp
    `framing.background_plane` fits to it: 1 for a plain colour or a gradient, less where the object
    touches the frame or the background is busy."""
    from .framing import background_plane, border_pixels

    off = np.abs(border_pixels(image) - border_pixels(background_plane(image, threshold))).max(-1)
    return float(np.mean(off <= threshold))


def busy_background(image: np.ndarray, threshold: float = 0.03) -> bool:
    """Whether the picture (H, W, 3) in [0, 1] may have a busy background: under PLAIN_SHARE of its
    border lies within `threshold` of the linear ramp `framing.background_plane` fits to it
    (`plain_share`). A plain colour or a gradient puts all of it there; an object the frame cuts off,
    or a texture atlas with plain patches, most of it, so the bar is high and the caller also keeps
    the plain guess."""
    return plain_share(image, threshold) < PLAIN_SHARE


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Overlap of two masks (H, W) bool."""
    return float((a & b).sum() / max(int((a | b).sum()), 1))


def _histogram(colours: np.ndarray) -> np.ndarray:
    """Normalised colour histogram (BINS^3) of (N, 3) colours in [0, 1], blurred by one bin so that a
    slightly different shade still counts."""
    from scipy import ndimage

    bins = np.clip((colours * BINS).astype(np.int64), 0, BINS - 1)
    flat = (bins[:, 0] * BINS + bins[:, 1]) * BINS + bins[:, 2]
    counts = np.bincount(flat, minlength=BINS ** 3).reshape(BINS, BINS, BINS).astype(np.float64)
    counts = ndimage.gaussian_filter(counts, 1.0, mode="constant")
    return counts / max(counts.sum(), 1e-12)


def _lookup(histogram: np.ndarray, image: np.ndarray) -> np.ndarray:
    bins = np.clip((image * BINS).astype(np.int64), 0, BINS - 1)
    return histogram[bins[..., 0], bins[..., 1], bins[..., 2]]


def object_colours(mesh, views: int = COLOUR_VIEWS, size: int = 64) -> np.ndarray:
    """The colours (N, 3) of the original `mesh` (MeshBatch, canonical frame) as pictures show it:
    its covered pixels seen from `views` directions all around, lit from beside the camera."""
    from ..render import Cameras, MeshRenderer, fibonacci_directions, lights_at
    from .registration import DISTANCE, _center_objects, _up_for

    directions = fibonacci_directions(views).to(mesh.positions)
    cameras = Cameras(DISTANCE * directions, torch.zeros_like(directions), _up_for(directions), 40.0)
    cameras = _center_objects(mesh, cameras, size)
    light = cameras.eye + torch.tensor([0.5, 0.5, 1.0], dtype=cameras.eye.dtype)
    with torch.no_grad():
        rgba = MeshRenderer(blend="hard")(mesh, cameras, lights_at(light), size, size,
                                          torch.zeros(views, 3, dtype=cameras.eye.dtype)).rgba
    rgba = rgba.cpu().numpy()
    return rgba[..., :3][rgba[..., 3] > 0.5]


def _grabcut(image: np.ndarray, seeds: np.ndarray, iterations: int = 5) -> np.ndarray:
    """GrabCut (OpenCV) of `image` (H, W, 3) in [0, 1] from `seeds` (H, W) of cv2.GC_* labels, on a
    copy at most CUT_SIZE pixels a side; the object's mask (H, W) at the picture's size."""
    import cv2

    height, width = image.shape[:2]
    scale = min(1.0, CUT_SIZE / max(height, width))
    small = (max(8, round(width * scale)), max(8, round(height * scale)))
    pixels = (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)[..., ::-1]  # OpenCV's BGR
    labels = seeds
    if scale < 1.0:
        pixels = cv2.resize(pixels, small, interpolation=cv2.INTER_AREA)
        labels = cv2.resize(seeds, small, interpolation=cv2.INTER_NEAREST)
    labels = np.ascontiguousarray(labels, dtype=np.uint8)
    if not np.isin(labels, (cv2.GC_BGD, cv2.GC_PR_BGD)).any() or not np.isin(labels, (cv2.GC_FGD, cv2.GC_PR_FGD)).any():
        return np.isin(seeds, (cv2.GC_FGD, cv2.GC_PR_FGD))  # one side only: nothing to cut
    models = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.setRNGSeed(0)
    cv2.grabCut(np.ascontiguousarray(pixels), labels, None, *models, iterations, cv2.GC_INIT_WITH_MASK)
    mask = np.isin(labels, (cv2.GC_FGD, cv2.GC_PR_FGD)).astype(np.uint8)
    if scale < 1.0:
        mask = cv2.resize(mask * 255, (width, height), interpolation=cv2.INTER_LINEAR) > 127
    return _largest_parts(mask.astype(bool))


def _largest_parts(mask: np.ndarray) -> np.ndarray:
    """The largest connected parts of `mask` that together hold KEEP_AREA of its area."""
    from scipy import ndimage

    labels, count = ndimage.label(mask)
    if count <= 1:
        return mask
    sizes = ndimage.sum(mask, labels, index=np.arange(1, count + 1))
    order = np.argsort(sizes)[::-1]
    keep = order[: int(np.searchsorted(np.cumsum(sizes[order]) / sizes.sum(), KEEP_AREA)) + 1] + 1
    return np.isin(labels, keep)


def guided_object_mask(image: np.ndarray, mesh) -> np.ndarray:
    """The object's pixels (H, W) bool in a picture (H, W, 3) in [0, 1] with a busy background, guided by
    the original `mesh`'s colours (see the module docstring). Pixels more like the object than like the
    picture at large seed the cut as probably object, the rest as probably background, and frame-edge
    pixels unlike the object as background."""
    import cv2
    from scipy import ndimage

    prior = _histogram(object_colours(mesh))
    everything = _histogram(image.reshape(-1, 3))
    ratio = np.log(_lookup(prior, image) + 1e-6) - np.log(_lookup(everything, image) + 1e-6)
    ratio = ndimage.uniform_filter(ratio, 5)
    seeds = np.where(ratio > 0, cv2.GC_PR_FGD, cv2.GC_PR_BGD).astype(np.uint8)
    edge = np.zeros(ratio.shape, dtype=bool)
    edge[:2], edge[-2:], edge[:, :2], edge[:, -2:] = True, True, True, True
    seeds[edge & (ratio < 0)] = cv2.GC_BGD
    return _grabcut(image, seeds)


def recut(image: np.ndarray, silhouette: np.ndarray) -> np.ndarray:
    """The object's pixels (H, W) bool in a picture (H, W, 3) in [0, 1], cut again by GrabCut seeded by
    the `silhouette` (H, W) bool of a registered camera: probably object inside it, probably background
    in a band of RECUT_BAND pixels around it (at 256^2), background beyond. Where a first cut took in a patch of
    the background with the object's colours (a dark square beside a dark object) or left out parts
    of it, the camera registered on that cut is off, but its silhouette lies mostly on the object."""
    import cv2
    from scipy import ndimage

    band = ndimage.binary_dilation(silhouette, iterations=max(1, round(RECUT_BAND * max(silhouette.shape) / 256)))
    seeds = np.full(silhouette.shape, cv2.GC_BGD, dtype=np.uint8)
    seeds[band] = cv2.GC_PR_BGD
    seeds[silhouette] = cv2.GC_PR_FGD
    return _grabcut(image, seeds)
