"""The public API: `wm = meshseal.load(); marked = wm.embed(mesh, bits); result = wm.detect(image)`."""

from __future__ import annotations

import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from .errors import MeshsealError
from .framing import boxes_from_mask, crop_boxes, object_mask
from .mesh import Mesh, normalize, to_z_up
from .models import WatermarkModel
from .models.io import load_model, read_metadata

WEIGHTS_DIR = Path(__file__).parent / "weights"
DEFAULT_MODEL = "default"

_Z_UP = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def shipped_models() -> list[dict]:
    """The models inside the package: name, n_bits, strategy, path."""
    models = []
    for path in sorted(WEIGHTS_DIR.glob("*.safetensors")):
        import json

        metadata = read_metadata(path)
        config = json.loads(metadata.get("config", "{}"))
        models.append({"name": path.stem, "n_bits": config.get("n_bits"), "strategy": config.get("strategy"),
                       "path": str(path)})
    return models


def resolve_model(name_or_path: str | None) -> Path:
    if name_or_path is None:
        name_or_path = DEFAULT_MODEL
    path = Path(name_or_path)
    if path.suffix == ".safetensors" or path.exists():
        return path
    shipped = WEIGHTS_DIR / f"{name_or_path}.safetensors"
    if shipped.is_file():
        return shipped
    names = ", ".join(m["name"] for m in shipped_models()) or "none"
    raise MeshsealError(f"unknown model '{name_or_path}' (shipped: {names}; or give a .safetensors path)")


def parse_bits(bits, n_bits: int) -> torch.Tensor:
    """'0101...' or a sequence of 0/1 -> float tensor (n_bits,); clear error on anything else."""
    if isinstance(bits, str):
        text = bits.strip()
        if not text or set(text) - {"0", "1"}:
            raise MeshsealError(f"message must be a string of 0 and 1, got '{bits[:80]}'")
        values = [int(c) for c in text]
    else:
        values = [int(v) for v in bits]
        if set(values) - {0, 1}:
            raise MeshsealError("message bits must be 0 or 1")
    if len(values) != n_bits:
        raise MeshsealError(f"message has {len(values)} bits; this model carries exactly {n_bits}")
    return torch.tensor(values, dtype=torch.float32)


@dataclass
class Detection:
    """What the decoder read from one picture.

    bits: '0101...'; logits: raw decoder outputs; bit_confidence: per-bit probability that the bit is
    right (sigmoid of |logit|); confidence: their mean. `box` is the object's square box (cx, cy, half).
    """

    bits: str
    logits: list[float]
    bit_confidence: list[float]
    confidence: float
    box: tuple[float, float, float]

    def to_dict(self) -> dict:
        return {"bits": self.bits, "confidence": round(self.confidence, 4),
                "bit_confidence": [round(c, 4) for c in self.bit_confidence],
                "box": [round(v, 1) for v in self.box]}


def _load_image(image) -> tuple[np.ndarray, np.ndarray | None]:
    """Path / PIL image / array / tensor -> (H, W, 3) float in [0, 1] and an alpha mask if it has one."""
    from PIL import Image, UnidentifiedImageError

    if isinstance(image, (str, Path)):
        path = Path(image)
        if not path.is_file():
            raise MeshsealError(f"{path}: no such image file")
        try:
            with Image.open(path) as opened:
                opened.load()
                image = opened.copy()
        except (UnidentifiedImageError, OSError) as error:
            raise MeshsealError(f"{path}: not a readable image ({str(error).splitlines()[0][:120]})") from None
    if isinstance(image, Image.Image):
        has_alpha = image.mode in ("RGBA", "LA") or (image.mode == "P" and "transparency" in image.info)
        rgba = np.asarray(image.convert("RGBA"), dtype=np.float32) / 255.0
        alpha = rgba[..., 3] > 0.5 if has_alpha and rgba[..., 3].min() < 0.5 else None
        return rgba[..., :3], alpha
    if torch.is_tensor(image):
        image = image.detach().cpu().numpy()
        if image.ndim == 3 and image.shape[0] in (3, 4) and image.shape[-1] not in (3, 4):
            image = image.transpose(1, 2, 0)
    array = np.asarray(image)
    if array.ndim != 3 or array.shape[-1] not in (3, 4):
        raise MeshsealError(f"expected an (H, W, 3) or (H, W, 4) image, got shape {array.shape}")
    array = array.astype(np.float32) / (255.0 if array.dtype == np.uint8 else 1.0)
    alpha = array[..., 3] > 0.5 if array.shape[-1] == 4 and array[..., 3].min() < 0.5 else None
    return array[..., :3], alpha


class Watermarker:
    """A trained model with the operations users need."""

    def __init__(self, model: WatermarkModel, name: str = "custom"):
        self.model = model.eval()
        self.name = name

    @property
    def n_bits(self) -> int:
        return self.model.n_bits

    @property
    def device(self) -> torch.device:
        return next(self.model.parameters()).device

    # ------------------------------------------------------------ embed
    @torch.no_grad()
    def embed(self, mesh: Mesh, bits) -> Mesh:
        """A copy of `mesh` carrying `bits` in its textures (and normals/uvs with a vertex encoder).

        Positions and faces never change. Textures of any size are marked at the model's working
        resolution and the residual is upsampled onto them.
        """
        message = parse_bits(bits, self.n_bits).to(self.device).unsqueeze(0)
        marked = mesh.copy()
        textured = [m for m in marked.materials if m.texture is not None]
        encoder = self.model
        if encoder.texture_encoder is not None and textured and marked.uvs is not None:
            for material in textured:
                texture = material.texture.to(self.device).permute(2, 0, 1).unsqueeze(0)
                material.texture = encoder.texture_encoder(texture, message)[0].permute(1, 2, 0).cpu()
        elif encoder.vertex_encoder is None:
            raise MeshsealError("the mesh has no texture with UVs to carry the watermark, and this model "
                                "only marks textures")
        elif encoder.texture_encoder is not None:
            print("meshseal: warning: no texture with UVs: only the vertex normals carry the mark", file=sys.stderr)
        if encoder.vertex_encoder is not None:
            rotation = _Z_UP if mesh.up_axis == "y" else torch.eye(3)
            canonical = normalize(to_z_up(replace(mesh, source=None)))
            uvs = marked.uvs if marked.uvs is not None else torch.zeros(mesh.n_vertices, 2)
            normals, new_uvs = encoder.vertex_encoder(canonical.positions.to(self.device)[None],
                                                      canonical.normals.to(self.device)[None],
                                                      uvs.to(self.device)[None], message)
            marked.normals = (normals[0].cpu() @ rotation).contiguous()  # back to the file's frame
            if marked.uvs is not None:
                marked.uvs = new_uvs[0].cpu()
        return marked

    # ------------------------------------------------------------ detect
    @torch.no_grad()
    def detect(self, images) -> Detection | list[Detection]:
        """Read the message from one picture or a list of pictures (paths, PIL images, arrays, tensors).

        The object is found (alpha channel, else the pixels that differ from the border colour), cropped
        to a square around it and resized to the decoder's framing, so any resolution and framing work.
        """
        single = not isinstance(images, (list, tuple))
        results = [self._detect_one(image) for image in ([images] if single else images)]
        return results[0] if single else results

    def _detect_one(self, image) -> Detection:
        pixels, alpha = _load_image(image)
        if alpha is not None:
            mask, background = alpha, np.zeros(3, dtype=np.float32)
            pixels = pixels * alpha[..., None]  # transparent pixels -> black, as in training renders
        else:
            mask, background = object_mask(pixels)
        box = boxes_from_mask(torch.from_numpy(mask)[None])
        tensor = torch.from_numpy(np.ascontiguousarray(pixels)).permute(2, 0, 1)[None].to(self.device)
        framed = crop_boxes(tensor, box, self.model.config.frame_size,
                            torch.tensor(background, dtype=tensor.dtype)[None].to(self.device))
        logits = self.model.decode(framed.clamp(0, 1))[0].cpu()
        confidence = torch.sigmoid(logits.abs())
        bits = "".join("1" if v > 0 else "0" for v in logits.tolist())
        return Detection(bits, logits.tolist(), confidence.tolist(), float(confidence.mean()),
                         tuple(float(v) for v in box[0]))


def load(model: str | None = None, device: str | None = None) -> Watermarker:
    """Load a shipped model by name (default: 'default') or a checkpoint path (.safetensors)."""
    path = resolve_model(model)
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    return Watermarker(load_model(path, device), path.stem)


__all__ = ["load", "Watermarker", "Detection", "shipped_models", "parse_bits"]
