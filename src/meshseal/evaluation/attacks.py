"""What happens to a picture on its way to the web, applied to 8-bit pictures as files would carry them.

Each attack is a function of an (H, W, 3) uint8 array and a numpy Generator that returns a new uint8
array (possibly of another size): lossy formats through Pillow's own encoders with their defaults
(JPEG with 4:2:0 chroma subsampling, as cameras, browsers and image hosts save), resizing as thumbnails
and re-uploads do, crops, a screenshot of a viewer window, and photometric edits. `ATTACKS` names the
suite `meshseal eval --attacks` runs on pictures (`asset_attacks` has those on the marked asset); `apply`
runs one by name.
"""

from __future__ import annotations

import io
from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # numpy and Pillow are imported where an attack runs: parsing a list of names needs neither
    import numpy as np


def _encode(picture: np.ndarray, format_: str, **options) -> np.ndarray:
    import numpy as np
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(picture).save(buffer, format=format_, **options)
    buffer.seek(0)
    with Image.open(buffer) as decoded:
        return np.asarray(decoded.convert("RGB")).copy()


def jpeg(quality: int, full_chroma: bool = False) -> Callable:
    """Saved as JPEG at `quality` (Pillow's defaults: 4:2:0 chroma subsampling; `full_chroma`: 4:4:4, as
    some tools save at high quality) and read back."""
    options = {"subsampling": 0} if full_chroma else {}
    return lambda picture, rng: _encode(picture, "JPEG", quality=quality, **options)


def webp(quality: int) -> Callable:
    """Saved as lossy WebP at `quality` and read back."""
    return lambda picture, rng: _encode(picture, "WEBP", quality=quality)


def resize(factor: float) -> Callable:
    """Resized by `factor` (bicubic, as most image tools)."""
    def attack(picture, rng):
        import numpy as np
        from PIL import Image

        height, width = picture.shape[:2]
        size = (max(8, round(width * factor)), max(8, round(height * factor)))
        return np.asarray(Image.fromarray(picture).resize(size, Image.Resampling.BICUBIC))
    return attack


def _central_window(height: int, width: int, keep: float) -> tuple[int, int, int, int]:
    """(top, left, h, w) of `central_crop(keep)`'s window in a height x width picture."""
    h, w = max(8, round(height * keep)), max(8, round(width * keep))
    return (height - h) // 2, (width - w) // 2, h, w


def central_crop(keep: float) -> Callable:
    """The central `keep` of each side."""
    def attack(picture, rng):
        top, left, h, w = _central_window(picture.shape[0], picture.shape[1], keep)
        return picture[top:top + h, left:left + w].copy()
    return attack


def screenshot(width: int = 400, height: int = 320, bar: int = 24) -> Callable:
    """The picture pasted at a random place of a `width` x `height` light-grey window with a darker
    `bar`-pixel title bar on top: a screenshot of a viewer (a picture larger than the window is shrunk
    to fit first)."""
    def attack(picture, rng):
        import numpy as np
        from PIL import Image

        canvas = np.full((height, width, 3), 236, dtype=np.uint8)
        canvas[:bar] = 60
        image = Image.fromarray(picture)
        room = (width, height - bar)
        if image.width > room[0] or image.height > room[1]:
            scale = min(room[0] / image.width, room[1] / image.height)
            image = image.resize((max(8, int(image.width * scale)), max(8, int(image.height * scale))),
                                 Image.Resampling.BICUBIC)
        top = bar + int(rng.integers(0, room[1] - image.height + 1))
        left = int(rng.integers(0, room[0] - image.width + 1))
        canvas[top:top + image.height, left:left + image.width] = np.asarray(image)
        return canvas
    return attack


def brightness_gamma(gain: float = 1.2, gamma: float = 0.9) -> Callable:
    """Brighter by `gain`, then a gamma curve (a photo editor's quick fix)."""
    def attack(picture, rng):
        import numpy as np

        x = np.clip(picture.astype(np.float64) / 255.0 * gain, 0.0, 1.0) ** gamma
        return np.round(x * 255.0).astype(np.uint8)
    return attack


def gaussian_noise(sigma: float = 2.0) -> Callable:
    """Additive Gaussian noise of `sigma` (in 8-bit levels)."""
    def attack(picture, rng):
        import numpy as np

        noisy = picture.astype(np.float64) + rng.normal(0.0, sigma, picture.shape)
        return np.clip(np.round(noisy), 0, 255).astype(np.uint8)
    return attack


def chained(*steps: Callable) -> Callable:
    """The attacks one after the other (a JPEG on the web, then a screenshot of the page that shows it)."""
    def attack(picture, rng):
        for step in steps:
            picture = step(picture, rng)
        return picture
    return attack


ATTACKS: dict[str, Callable] = {
    "none": lambda picture, rng: picture.copy(),
    "jpeg95": jpeg(95), "jpeg90": jpeg(90), "jpeg75": jpeg(75), "jpeg50": jpeg(50),
    "jpeg95_444": jpeg(95, full_chroma=True), "jpeg90_444": jpeg(90, full_chroma=True),
    "webp80": webp(80),
    "resize0.5": resize(0.5), "resize0.75": resize(0.75), "resize1.5": resize(1.5),
    "crop0.8": central_crop(0.8),
    "screenshot": screenshot(),
    "jpeg90_screenshot": chained(jpeg(90), screenshot()), "jpeg75_screenshot": chained(jpeg(75), screenshot()),
    "jpeg75_crop0.8": chained(jpeg(75), central_crop(0.8)),
    "brightness": brightness_gamma(),
    "noise2": gaussian_noise(2.0),
}
GEOMETRIC = {"resize0.5", "resize0.75", "resize1.5", "crop0.8", "screenshot", "jpeg90_screenshot", "jpeg75_screenshot",
             "jpeg75_crop0.8"}  # the camera of the picture changes


CROPS = {"crop0.8": 0.8, "jpeg75_crop0.8": 0.8}  # the central crops: `keep` of each side


def cropped_camera(name: str, cameras, height: int, width: int):
    """The camera (`render.Cameras`) that took the picture attack `name` leaves of a height x width
    picture taken with `cameras` (centred principal point), where the attack is a central crop (CROPS);
    None for any other attack that changes the frame (a screenshot's canvas is placed at random). With
    it a crop is read with its camera known, so that what registration costs there can be told from
    what the crop took (`evaluation.evaluate_registered`)."""
    if name not in CROPS:
        return None
    import math
    from dataclasses import replace

    top, left, h, w = _central_window(height, width, CROPS[name])
    if h != w or height != width:  # a square window of a square picture (as `registration.crop_intrinsics`)
        return None
    half, centre_x, centre_y = h / 2, left + w / 2, top + h / 2
    fov = math.degrees(2 * math.atan(math.tan(math.radians(cameras.fov_y) / 2) * 2 * half / height))
    return replace(cameras, fov_y=fov, principal=((width / 2 - centre_x) / half, (centre_y - height / 2) / half))


# The asset attacks (`asset_attacks.ASSET_ATTACKS`, on the marked mesh before it is rendered), named here
# so that parsing a list needs neither torch nor the mesh package.
ASSET_NAMES = ("texture_jpeg90", "texture_half", "texture_bc1", "texture_bc7", "obj_glb", "decimate0.5")


def parse(text: str) -> list[str]:
    """'jpeg90,webp80,texture_bc1' or 'all' -> attack names (pictures' and assets'); an unknown name is a
    ValueError naming the known ones."""
    known = [*ATTACKS, *ASSET_NAMES]
    names = known if text.strip() == "all" else [t.strip() for t in text.split(",") if t.strip()]
    unknown = [name for name in names if name not in known]
    if unknown or not names:
        raise ValueError(f"unknown attack(s) {', '.join(unknown) or '(none given)'}: one or more of "
                         f"{', '.join(known)} (comma-separated), or all")
    return names


def apply(name: str, picture: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Attack `name` on an (H, W, 3) uint8 picture -> a uint8 picture."""
    import numpy as np

    return ATTACKS[name](np.ascontiguousarray(picture, dtype=np.uint8), rng)
