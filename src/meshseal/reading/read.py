"""One picture's evidence before any decision: the picture loaded, its object found, its camera taken
from its metadata or found by registration (informed methods), and the method's evidence read under
that camera; blind methods read the object alone. `second_look` may read a registered picture again."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from ..errors import MeshsealError
from ..threads import reading_threads, revisit
from .framing import box_from_points, boxes_from_mask, estimate_background, inner_picture, object_mask
from .pictures import camera_from_metadata, load_picture_and_codecs, picture_name

MIN_OBJECT_PIXELS = 64  # fewer object pixels than this: nothing to read
REGISTER_MIN_SIDE = 96  # an object whose box is narrower than this many pixels is registered on a copy enlarged ...
REGISTER_MAX_FACTOR = 4  # ... by a whole factor, at most this one ...
REGISTER_MAX_SIDE = 1024  # ... and to at most this many pixels a side
RIM_BELOW = 48  # an object whose box is narrower than this many pixels, on a plain background, is polished on its rim too ...
RIM_PIXELS_BELOW = 5000  # ... and one of fewer pixels than this, more quickly: one round, on the sharp pixels alone


@dataclass
class Reading:
    """One picture's evidence before the decision (`Method.decide`): matched-filter cell sums or logits."""

    evidence: torch.Tensor
    box: tuple[float, float, float]
    camera: str | None
    registration_iou: float | None
    found: object = None  # the Cameras used to un-render (informed methods)
    tries: int = 1  # what the decision multiplies the p-value by for the cameras a second look could try
    second_look: tuple = ()  # registered: (picture, mask, Registration.alternatives), until `second_look.look_again`
    object_mask_of: Callable[[], torch.Tensor] | None = None  # camera from metadata: makes `object_mask`

    @property
    def object_mask(self) -> torch.Tensor | None:
        """Camera from metadata: the picture's object (H, W) bool, for `why_not` (made when asked: a
        picture whose mark is found never needs it)."""
        return None if self.object_mask_of is None else self.object_mask_of()


class ObjectMask:
    """A picture's object (H, W) bool tensor (`framing.object_mask`, untrimmed), made on the first call
    from the picture's pixels (H, W, 3) unless given as `mask`. Pickled (a worker's reading sent back)
    as the mask itself, made then."""

    def __init__(self, pixels: np.ndarray | None, mask: np.ndarray | None = None):
        self._pixels = pixels
        self._mask = None if mask is None else np.ascontiguousarray(mask > 0.5)

    def __call__(self) -> torch.Tensor:
        if self._mask is None:
            self._mask = np.ascontiguousarray(object_mask(self._pixels, trim=False)[0] > 0.5)
            self._pixels = None
        return torch.from_numpy(self._mask)

    def __getstate__(self) -> dict:
        self()
        return {"_pixels": None, "_mask": self._mask}


CLEARLY_NOT_EMPTY = 4 * MIN_OBJECT_PIXELS  # pixels off the border's colour that make a picture clearly not empty


def clearly_not_empty(pixels: np.ndarray, threshold: float = 0.03) -> bool:
    """Whether a picture (H, W, 3) clearly shows something: CLEARLY_NOT_EMPTY pixels or more differ
    from the median colour of its border by over `threshold` in some channel. A cheap look, for a
    reading whose camera is known (it needs no object mask); a picture it does not clear gets
    `framing.object_mask`'s count, as every registered picture does."""
    background = estimate_background(pixels)
    low, high = background - threshold, background + threshold
    off = np.zeros(pixels.shape[:2], dtype=bool)
    for channel in range(pixels.shape[-1]):  # channel by channel: a reduction over a last axis of 3 costs ten times
        plane = pixels[..., channel]
        off |= (plane < low[channel]) | (plane > high[channel])
    return int(np.count_nonzero(off)) >= CLEARLY_NOT_EMPTY


def object_side(mask: np.ndarray) -> int:
    """The longer side, in pixels, of the box of a picture's object pixels `mask` (H, W); 0 where none."""
    rows, columns = np.nonzero(mask > 0.5)
    if len(rows) == 0:
        return 0
    return max(int(rows.max() - rows.min()) + 1, int(columns.max() - columns.min()) + 1)


def registration_factor(mask: np.ndarray) -> int:
    """The whole factor by which a picture whose object's pixels are `mask` (H, W) is enlarged for
    registration: 1, or enough to bring the object's box to REGISTER_MIN_SIDE pixels (within
    REGISTER_MAX_FACTOR and REGISTER_MAX_SIDE). A luminance mark needs the camera to a few hundredths
    of a pixel; on an object under a hundred pixels wide in a resized picture (whose pixels average
    the texture) the texture stage, comparing the picture with renders sampled at its own coarse
    pixels, stops a tenth of a pixel or more off, and on a copy twice as large it does not. A larger
    object gains nothing (an enlarged point-sampled render is not a finer one) and takes longer."""
    side = object_side(mask)
    if side == 0:
        return 1
    factor = min(REGISTER_MAX_FACTOR, -(-REGISTER_MIN_SIDE // side), REGISTER_MAX_SIDE // max(mask.shape))
    return max(1, factor)


def enlarged(picture: torch.Tensor, masks: list[torch.Tensor], recut, factor: int):
    """The picture (3, H, W) enlarged `factor` times (bicubic), its object guesses (H, W, or a function
    making one, or None, when it is reached) likewise (each pixel repeated) and `recut` (an enlarged
    silhouette -> an enlarged guess) working at the picture's own size: what `register_with_masks`
    takes, at the size it registers at."""
    if factor == 1:
        return picture, masks, recut
    import torch.nn.functional as F

    big = F.interpolate(picture[None], scale_factor=factor, mode="bicubic", align_corners=False)[0].clamp(0, 1)
    grow = lambda m: m.repeat_interleave(factor, 0).repeat_interleave(factor, 1)  # noqa: E731

    def again(silhouette: np.ndarray) -> np.ndarray:
        small = silhouette.reshape(silhouette.shape[0] // factor, factor, -1, factor).mean((1, 3)) > 0.5
        return np.repeat(np.repeat(recut(small), factor, 0), factor, 1)
    grown = lambda m: grow(m) if torch.is_tensor(m) else (lambda: None if (g := m()) is None else grow(g))  # noqa: E731
    return big, [grown(m) for m in masks], (again if recut is not None else None)


class Reader:
    """Reads pictures for one `methods.Method`, keeping what it worked out for the last original."""

    def __init__(self, method):
        self.method = method
        self._cpu_of: tuple | None = None  # (prepared original, its copy on the CPU for registration)

    @property
    def device(self) -> torch.device:
        return self.method.device

    def read(self, image, original, register: bool = False, fov_y: float = 60.0, camera=None,
             quick: bool = False) -> Reading:
        """One picture's evidence; `original` from `Method.prepare`, None for blind methods. The camera
        comes from `camera` (one `Cameras`, canonical frame: it overrides the rest), else the picture's
        metadata (unless `register`), else registration assuming a vertical field of view `fov_y`
        (`quick`: without its recut and retry, `registration.register_with_masks`)."""
        pixels, alpha, camera_text, codecs, luma = load_picture_and_codecs(image)
        revisit()  # one of many pictures: the thread count again from the jobs running now
        with reading_threads(pixels.shape[0] * pixels.shape[1]):
            return self._read(image, pixels, alpha, camera_text, codecs, luma, original, register, fov_y, camera, quick)

    def _read(self, image, pixels, alpha, camera_text, codecs, luma, original, register, fov_y, camera,
              quick=False) -> Reading:
        """`read` of the loaded picture (`load_picture_and_codecs`'s pixels, alpha, camera text, codecs)."""
        given = camera is not None
        from_metadata = original is not None and camera_text is not None and not register and not given
        if alpha is not None:
            pixels = pixels * alpha[..., None]  # transparent pixels -> black, as in training renders
            mask, background = alpha, np.zeros(3, dtype=np.float32)
        else:  # the silhouette's edge matters only to registration
            inner = None if (given or from_metadata) else inner_picture(pixels)
            if inner is not None:  # a picture within a picture (a screenshot): read the inner one, in its own frame
                top, bottom, left, right = inner
                pixels = np.ascontiguousarray(pixels[top:bottom, left:right])
                codecs, luma = None, None  # its blocks no longer lie on the file's 8x8 grid
            if (given or from_metadata) and clearly_not_empty(pixels):
                mask, background = None, None  # the camera says where the object is; the mask only if asked
            else:
                mask, background = object_mask(pixels, trim=not (given or from_metadata))
        if mask is not None and int(mask.sum()) < MIN_OBJECT_PIXELS:  # answer at once rather than search an empty picture
            what = "transparent, or nearly" if alpha is not None else "one plain colour, or nearly"
            raise MeshsealError(f"{picture_name(image)}: no object found (the picture is {what})")
        tensor = torch.from_numpy(np.ascontiguousarray(pixels)).permute(2, 0, 1)[None].to(self.device)
        if from_metadata:
            camera = camera_from_metadata(camera_text, self.device, picture_name(image))
        if camera is not None:  # the known camera says where the object is: no need to search for it
            from ..render import clip_to_screen

            height, width = pixels.shape[:2]
            corners = clip_to_screen(camera.world_to_clip(original.positions, width / height), height, width)
            box = tuple(float(v) for v in box_from_points(corners.reshape(-1, 2), height, width)[0])
            evidence = self.method.evidence(original, self._expect_codecs(tensor.clamp(0, 1), codecs, luma), camera)
            if from_metadata:  # kept for `why_not`: does the picture show this mesh where its camera says?
                return Reading(evidence, box, "metadata", None, camera, object_mask_of=ObjectMask(pixels, mask))
            return Reading(evidence, box, "given", None, camera)
        background_tensor = torch.tensor(background, dtype=tensor.dtype)
        if original is None:
            box = tuple(float(v) for v in boxes_from_mask(torch.from_numpy(mask)[None])[0])
            return Reading(self.method.blind_evidence(pixels, mask, background_tensor), box, None, None)
        from ..render import compiled
        from .registration import polish, polish_composited, register_with_masks

        compiled.load()  # registration renders thousands of views: the compiled kernels pay at once

        guesses, recut = self._object_guesses(pixels, mask, alpha, original)
        factor = registration_factor(mask)
        picture, guesses, recut = enlarged(tensor[0].cpu(), guesses, recut, factor)
        found = register_with_masks(self.on_cpu(original), picture, guesses, background_tensor.cpu(),
                                    fov_y=fov_y, recut=recut, quick=quick)
        # a camera is the same for the picture at any size: its last hundredths of a pixel at the picture's own
        camera, own_mask = found.camera, torch.from_numpy(np.ascontiguousarray(mask))[None].float()
        small = object_side(mask) < RIM_BELOW
        few = small or int(np.count_nonzero(mask > 0.5)) < RIM_PIXELS_BELOW
        behind = self._plain_background(pixels, alpha) if few else None
        if behind is not None:  # an object of few pixels on a plain background: its rim says where it lies
            rim = {} if small else {"sigmas": (0.0,), "rounds": 1}  # a few thousand pixels: one sharp round
            camera = polish_composited(self.on_cpu(original), camera, tensor.cpu().clamp(0, 1), own_mask, behind,
                                       **rim)
        camera = polish(self.on_cpu(original), camera, tensor.cpu().clamp(0, 1), own_mask).to(self.device)
        # one tensor for this reading and the second look: the codec found once
        seen = self._expect_codecs(tensor.clamp(0, 1), codecs, luma)
        evidence = self.method.evidence(original, seen, camera)
        second_look = (seen.cpu(), torch.from_numpy(np.ascontiguousarray(mask)), found.alternatives)
        return Reading(evidence, tuple(float(v) / factor for v in found.box), "registered", found.iou, camera,
                       second_look=second_look)

    @staticmethod
    def _plain_background(pixels: np.ndarray, alpha) -> torch.Tensor | None:
        """The background (1, 3, H, W) behind the object of a picture (H, W, 3) whose background is plain
        (a colour or a ramp, `framing.background_plane`, over PLAIN_SHARE of its border) or transparent
        (black, as its pixels were made); None where it is busy."""
        from .framing import background_plane
        from .segmentation import PLAIN_SHARE, plain_share

        if alpha is not None:
            return torch.zeros(1, 3, *pixels.shape[:2])
        if plain_share(pixels) < PLAIN_SHARE:
            return None
        plane = np.ascontiguousarray(background_plane(pixels), dtype=np.float32)
        return torch.from_numpy(plane).permute(2, 0, 1)[None].clamp(0, 1)

    @staticmethod
    def _expect_codecs(seen: torch.Tensor, codecs: list | None, luma=None) -> torch.Tensor:
        """`seen`, with the codecs its file says saved it noted for the codec step (`compression.expect`:
        a JPEG file's own tables, none for a PNG `meshseal render` wrote; None: the step searches), and
        a JPEG file's luminance steps for reading the mark through them (`compression.expect_luma`)."""
        from . import compression

        if codecs is not None:
            compression.expect(seen, [codecs])
        if luma is not None:
            compression.expect_luma(seen, [luma])
        return seen

    def _object_guesses(self, pixels: np.ndarray, mask: np.ndarray, alpha, original):
        """The object's pixels as registration should try them, and how to cut them again from a
        registered silhouette (None where the picture's alpha channel gives them): the plain-background
        `mask`, and where the background may be busy (`segmentation.busy_background`) a cut guided by the
        original's colours too, unless the two agree: first where under PLAIN_FIRST of the border is
        plain, second where more is (an object the frame cuts off on a plain background, which the
        plain mask finds and the colour-guided cut may lose parts of), and then cut only if
        registration reaches it (a function in the list: the cut renders the original 16 times);
        `segmentation.recut` of the picture (a dark object on a dark backdrop loses parts of it to the
        plain-background mask, too)."""
        from .segmentation import (GUESSES_AGREE, PLAIN_FIRST, PLAIN_SHARE, guided_object_mask, mask_iou,
                                   plain_share, recut)

        def guided() -> torch.Tensor | None:
            cut = guided_object_mask(pixels, self.on_cpu(original))
            if int(cut.sum()) < MIN_OBJECT_PIXELS or mask_iou(cut, mask) >= GUESSES_AGREE:
                return None
            return torch.from_numpy(np.ascontiguousarray(cut))

        guesses = [torch.from_numpy(np.ascontiguousarray(mask))]
        share = 1.0 if alpha is not None else plain_share(pixels)
        if share < PLAIN_FIRST:
            cut = guided()
            if cut is not None:
                guesses.insert(0, cut)
        elif share < PLAIN_SHARE:  # cut only if the plain mask's registration is not confirmed
            guesses.append(guided)
        again = None if alpha is not None else (lambda silhouette: recut(pixels, silhouette))
        return guesses, again

    def on_cpu(self, original):
        """The prepared original on the CPU, where registration runs whatever the model's device (its
        many small Gauss-Newton steps are written and tested for the CPU); kept for the next picture."""
        if original.positions.device.type == "cpu":
            return original
        if self._cpu_of is None or self._cpu_of[0] is not original:
            self._cpu_of = (original, original.to("cpu"))
        return self._cpu_of[1]
