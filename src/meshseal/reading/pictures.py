"""Pictures in and out: any file PIL reads, a PIL image, an array or a tensor -> RGB floats, the alpha
mask if it has one, and the camera that `meshseal render` writes into a PNG's metadata
(`image_bytes`, `camera_to_dict`)."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import torch

from ..errors import MeshError, MeshsealError

MIN_PICTURE_SIDE = 16  # smaller pictures cannot show the object's texture; refused at once
_HIGH_DEPTH = {"I": 65535.0, "I;16": 65535.0, "I;16B": 65535.0, "I;16L": 65535.0, "I;16N": 65535.0, "F": 1.0}


def picture_name(image) -> str:
    return str(image) if isinstance(image, (str, Path)) else "picture"


def _pil_to_arrays(image, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Any PIL picture -> (H, W, 3) float32 RGB in [0, 1] and its alpha (H, W) in [0, 1] (None if it has
    none), converted once: EXIF rotation applied, 16-bit and float grey scaled by their range, grey,
    palette, CMYK, YCbCr, ... through PIL's own conversions."""
    from PIL import ImageOps

    try:
        image = ImageOps.exif_transpose(image)
    except Exception:  # a broken EXIF block: keep the pixels as stored
        pass
    if image.mode in _HIGH_DEPTH:
        grey = np.asarray(image, dtype=np.float64) / _HIGH_DEPTH[image.mode]
        if not np.isfinite(grey).all():
            raise MeshsealError(f"{name}: picture contains NaN or infinite values")
        rgb = np.repeat(np.clip(grey, 0.0, 1.0)[..., None], 3, axis=-1).astype(np.float32)
        return rgb, None
    has_alpha = "A" in image.getbands() or "transparency" in image.info
    try:
        converted = image.convert("RGBA") if has_alpha else image.convert("RGB")
    except ValueError:  # modes PIL converts only through RGB (e.g. LAB, HSV)
        try:
            converted = image.convert("RGB")
        except ValueError:
            raise MeshsealError(f"{name}: picture mode {image.mode} cannot be converted to RGB") from None
    array = np.asarray(converted, dtype=np.float32) / 255.0
    return array[..., :3], (array[..., 3] if array.shape[-1] == 4 else None)


def load_picture(image) -> tuple[np.ndarray, np.ndarray | None, str | None]:
    """Path / PIL image / array / tensor -> (H, W, 3) float in [0, 1], an alpha mask if it has one, and
    the camera metadata text if the picture carries one (see `image_bytes`).

    A path must name a regular file holding a picture PIL reads, within PIL's decompression-bomb pixel
    limit, at least MIN_PICTURE_SIDE pixels a side; anything else is a MeshsealError naming it.
    """
    return load_picture_and_codecs(image)[:3]


def file_codecs(image) -> list | None:
    """The codecs the codec step (`reading.compression.recompressed`) should try on a PIL picture, from
    its file alone, or None where the file does not say (search them all): a PNG carrying the camera
    chunk `meshseal render` writes was saved losslessly by it, since no lossy format keeps that chunk
    ([]); a JPEG file whose quantization tables and chroma subsampling are one of the candidates
    (`compression.listed_jpeg`; upright 3-component pictures) tries that one alone."""
    from ..mesh.validate import JPEG_CODEC_KEY, _jpeg_codec
    from .compression import listed_jpeg

    if image.format == "PNG" and isinstance(image.info.get(CAMERA_KEY), str):
        return []
    if image.format == "JPEG":
        codec = listed_jpeg(image.info[JPEG_CODEC_KEY] if JPEG_CODEC_KEY in image.info else _jpeg_codec(image))
        return None if codec is None else [codec]
    return None


def file_luma_table(image) -> np.ndarray | None:
    """A JPEG file's own luminance quantisation steps (8, 8), natural order (upright 3-component
    pictures, as `file_codecs`), or None: what `compression.dequantized` reads the picture through."""
    from ..mesh.validate import JPEG_CODEC_KEY, _jpeg_codec

    if image.format != "JPEG":
        return None
    codec = image.info[JPEG_CODEC_KEY] if JPEG_CODEC_KEY in image.info else _jpeg_codec(image)
    if codec is None or 0 not in codec[1] or len(codec[1][0]) != 64:
        return None
    return np.asarray(codec[1][0], dtype=np.float64).reshape(8, 8)


def load_picture_and_codecs(image) -> tuple[np.ndarray, np.ndarray | None, str | None, list | None, np.ndarray | None]:
    """`load_picture`, the codecs its file says saved it (`file_codecs`; None for arrays, tensors
    and files that do not say) and a JPEG file's luminance steps (`file_luma_table`, else None)."""
    from PIL import Image

    from ..mesh.validate import read_image

    name = picture_name(image)
    codecs, luma = None, None
    if isinstance(image, (str, Path)):
        image = read_image(Path(image), name, MIN_PICTURE_SIDE)
    if isinstance(image, Image.Image):
        camera_text = image.info.get(CAMERA_KEY)
        codecs, luma = file_codecs(image), file_luma_table(image)
        pixels, alpha = _pil_to_arrays(image, name)
        camera_text = camera_text if isinstance(camera_text, str) else None
    else:
        if torch.is_tensor(image):
            image = image.detach().cpu().numpy()
            if image.ndim == 3 and image.shape[0] in (3, 4) and image.shape[-1] not in (3, 4):
                image = image.transpose(1, 2, 0)
        array = np.asarray(image)
        if array.ndim != 3 or array.shape[-1] not in (3, 4) or not (array.dtype == np.uint8 or
                                                                    np.issubdtype(array.dtype, np.floating)):
            raise MeshsealError(f"expected an (H, W, 3) or (H, W, 4) uint8 or float image, got shape "
                                f"{array.shape} ({array.dtype})")
        array = array.astype(np.float32) / (255.0 if array.dtype == np.uint8 else 1.0)
        if not np.isfinite(array).all():
            raise MeshsealError(f"{name}: picture contains NaN or infinite values")
        pixels, alpha, camera_text = array[..., :3], (array[..., 3] if array.shape[-1] == 4 else None), None
    height, width = pixels.shape[:2]
    if min(height, width) < MIN_PICTURE_SIDE:
        raise MeshsealError(f"{name}: picture is {width}x{height} pixels, too small (at least "
                            f"{MIN_PICTURE_SIDE} pixels a side)")
    mask = alpha > 0.5 if alpha is not None and alpha.min() < 0.5 else None
    return pixels, mask, camera_text, codecs, luma


def camera_from_metadata(text: str, device, name: str = "picture"):
    """The camera a `meshseal render` picture carries in its PNG text chunk."""
    import json


    try:
        return camera_from_dict(json.loads(text)).to(device)
    except (ValueError, RecursionError):
        raise MeshsealError(f"{name}: the picture's camera metadata is not valid JSON") from None
    except MeshsealError as error:
        raise MeshsealError(f"{name}: {error}") from None


CAMERA_KEY = "meshseal:camera"


def image_bytes(image, fmt: str = "PNG", camera=None, quality: int = 90) -> bytes:
    """Encode an image; a PNG may carry the camera that rendered it (one `Cameras` element, in the
    canonical frame) as a text chunk, which informed detection uses instead of registering."""
    buffer = io.BytesIO()
    options = {"quality": quality} if fmt == "JPEG" else {}
    if camera is not None and fmt == "PNG":
        from PIL.PngImagePlugin import PngInfo

        info = PngInfo()
        info.add_text(CAMERA_KEY, json.dumps(camera_to_dict(camera)))
        options["pnginfo"] = info
    image.save(buffer, format=fmt, **options)
    return buffer.getvalue()


def camera_to_dict(camera) -> dict:
    return {"eye": camera.eye[0].tolist(), "at": camera.at[0].tolist(), "up": camera.up[0].tolist(),
            "fov_y": camera.fov_y, "principal": list(camera.principal), "frame": "canonical"}


def camera_from_dict(values: dict):
    """The inverse of `camera_to_dict`; raises MeshError on anything malformed."""
    import math

    from ..render.cameras import Cameras

    try:
        eye, at, up = (torch.tensor([[float(v) for v in values[key]]]) for key in ("eye", "at", "up"))
        fov = float(values["fov_y"])
        principal = tuple(float(v) for v in values.get("principal", (0.0, 0.0)))
        if eye.shape != (1, 3) or at.shape != (1, 3) or up.shape != (1, 3) or len(principal) != 2:
            raise ValueError("bad shape")
        if not (0.0 < fov < 180.0) or not all(math.isfinite(v) for v in eye.tolist()[0] + at.tolist()[0] + up.tolist()[0]):
            raise ValueError("bad values")
    except (KeyError, TypeError, ValueError) as error:
        raise MeshError(f"malformed camera metadata ({error})") from None
    return Cameras(eye, at, up, fov, principal=principal)
