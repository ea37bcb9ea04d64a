"""The public API: `wm = meshseal.load(); marked = wm.embed(mesh, bits); result = wm.detect(image)`."""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from .errors import MeshsealError
from .framing import box_from_points, boxes_from_mask, crop_boxes, inner_picture, object_mask
from .mesh import Mesh, normalize, to_z_up
from .metrics import BUDGET_VIEWS, MAX_FLIP
from .models import WatermarkModel
from .models.io import load_model, read_metadata
from .models.spread import palette_share, texels_used

WEIGHTS_DIR = Path(__file__).parent / "weights"
DEFAULT_MODEL = "default"

_Z_UP = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def shipped_models() -> list[dict]:
    """The models inside the package: name, raw bits, payload bits (after error correction and header;
    None without a payload schema), strategy, whether detection needs the original mesh (informed) and
    whether its soft bits are calibrated z-scores (p-values, decisions), path."""
    import json

    from .payload import SCHEMAS, payload_bits

    models = []
    for path in sorted(WEIGHTS_DIR.glob("*.safetensors")):
        config = json.loads(read_metadata(path).get("config", "{}"))
        n_bits, decoder = config.get("n_bits"), config.get("decoder")
        models.append({"name": path.stem, "n_bits": n_bits,
                       "payload_bits": payload_bits(n_bits) if n_bits in SCHEMAS else None,
                       "strategy": config.get("strategy"), "informed": decoder in ("uv", "matched"),
                       "calibrated": decoder == "matched", "path": str(path)})
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
    """What detection read from one picture (or, pooled, from several pictures of one asset).

    detected: whether the picture carries a mark under the key, at the false-positive rate
    `payload.FPR` (None for models without calibrated soft bits); p_value: the chance that a picture
    without such a mark scores this high (see payload.detection_pvalue / match_pvalue); message: the
    decoded text or ID, None when not detected or not decodable; bits: the raw hard bits '0101...';
    soft: the soft bits (matched-filter z, mean 0 and variance 1 each without a mark; learned models: logits);
    errors_corrected: raw bits the error correction flipped. `box` is the object's square box (cx, cy,
    half) in the picture; `camera` 'metadata' or 'registered' for informed models. `silhouette_iou`:
    the original's silhouette under the picture's camera against the picture's object (registered
    pictures; pictures whose camera came from metadata when they read no mark); `reason`: why no mark
    was read, where a plausible mistake explains it (`Watermarker.why_not`), else None.
    """

    bits: str
    soft: list[float]
    p_value: float | None
    detected: bool | None
    message: str | int | None
    errors_corrected: int | None
    box: tuple[float, float, float] | None
    camera: str | None = None
    registration_iou: float | None = None
    pictures: int = 1
    silhouette_iou: float | None = None
    reason: str | None = None

    def to_dict(self) -> dict:
        result = {"detected": self.detected, "p_value": None if self.p_value is None else float(f"{self.p_value:.4g}"),
                  "message": self.message, "bits": self.bits, "errors_corrected": self.errors_corrected,
                  "soft": [round(v, 3) for v in self.soft]}
        if self.box is not None:
            result["box"] = [round(v, 1) for v in self.box]
        if self.camera is not None:
            result["camera"] = self.camera
        if self.registration_iou is not None:
            result["registration_iou"] = round(self.registration_iou, 4)
        if self.pictures != 1:
            result["pictures"] = self.pictures
        if self.silhouette_iou is not None:
            result["silhouette_iou"] = round(self.silhouette_iou, 4)
        if self.reason is not None:
            result["reason"] = self.reason
        return result


@dataclass
class _Reading:
    """One picture's evidence before the decision: matched-filter cell sums (spread models) or logits."""

    evidence: torch.Tensor
    box: tuple[float, float, float]
    camera: str | None
    registration_iou: float | None
    found: object = None  # the Cameras used to un-render (informed models)
    tries: int = 1  # what `decide` multiplies the p-value by for the cameras a second look could try
    second_look: tuple = ()  # registered: (picture, mask, Registration.alternatives), until `look_again`
    object_mask: torch.Tensor | None = None  # camera from metadata: the picture's object (H, W) bool, for `why_not`


MIN_PICTURE_SIDE = 16  # smaller pictures cannot show the object's texture; refused at once
MIN_OBJECT_PIXELS = 64  # fewer object pixels than this: nothing to read
_HIGH_DEPTH = {"I": 65535.0, "I;16": 65535.0, "I;16B": 65535.0, "I;16L": 65535.0, "I;16N": 65535.0, "F": 1.0}


def _name(image) -> str:
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


def _load_image(image) -> tuple[np.ndarray, np.ndarray | None, str | None]:
    """Path / PIL image / array / tensor -> (H, W, 3) float in [0, 1], an alpha mask if it has one, and
    the camera metadata text if the picture carries one (see mesh.io.image_bytes).

    A path must name a regular file holding a picture PIL reads, within PIL's decompression-bomb pixel
    limit, at least MIN_PICTURE_SIDE pixels a side; anything else is a MeshsealError naming it.
    """
    from PIL import Image

    from .mesh.io import CAMERA_KEY
    from .mesh.validate import read_image

    name = _name(image)
    if isinstance(image, (str, Path)):
        image = read_image(Path(image), name, MIN_PICTURE_SIDE)
    if isinstance(image, Image.Image):
        camera_text = image.info.get(CAMERA_KEY)
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
    return pixels, mask, camera_text


PALETTE_WARNING = 0.5  # embed warns when this share of the textured surface has faces without UV area
SHARPEN_ROUNDS = 2  # a second look sharpens the registered camera again (light refitted) where the first round's reading hints at a mark
SHOWS_MESH_BELOW = 0.8  # `why_not`: an object overlapping the original's silhouette less than this may be another mesh
LOOK_AGAIN_BELOW = 0.05  # a second look finishes the other views where the first reading's p-value is under this, else those whose rough reading's is


class Watermarker:
    """A trained model with the operations users need."""

    def __init__(self, model: WatermarkModel, name: str = "custom"):
        self.model = model.eval()
        self.name = name
        self._grids_of: tuple | None = None  # (prepared original, encoder, its grids_to_read)
        self._cpu_of: tuple | None = None  # (prepared original, its copy on the CPU for registration)
        self._own_of: tuple | None = None  # (prepared original, key seed, own_mark_pvalue) for `why_not`

    @property
    def n_bits(self) -> int:
        return self.model.n_bits

    @property
    def device(self) -> torch.device:
        return self.model.device

    # ------------------------------------------------------------ embed
    @torch.no_grad()
    def embed(self, mesh: Mesh, message=None, *, bits=None, key: str | bytes | None = None,
              strength: float = 1.0, warn: bool = True) -> Mesh:
        """A copy of `mesh` carrying `message` (text, an int ID or a `payload.Message`; error-corrected
        and keyed, see `payload`) or raw `bits` ('0101...' or a sequence of 0/1 of the model's length,
        no error correction) in its textures (and normals/uvs with a vertex encoder). `key` (None: the
        public key) keys both the payload and the mark's pattern.

        Positions never change; spread-spectrum models first give faces without UV area (a palette
        texture) charts of their own (`layout`: added vertices and a taller texture, rendered as
        before). Learned encoders mark textures of any size at the model's working resolution and
        upsample the residual; spread-spectrum models mark at full resolution, `strength` times their
        default amplitude (2: 6 dB louder and more robust; 0.5: quieter). `warn`: print warnings about
        the mesh (a palette texture, no texture) to stderr.
        """
        from . import payload

        if not 0.0 < strength <= 10.0:
            raise MeshsealError(f"strength must be in (0, 10], got {strength}")
        if (message is None) == (bits is None):
            raise MeshsealError("give either a message or raw bits")
        if bits is None and isinstance(message, (list, tuple, torch.Tensor)):
            bits, message = message, None  # a sequence of 0/1 is raw bits
        raw = parse_bits(bits, self.n_bits) if bits is not None else payload.encode(message, key, self.n_bits)
        message = raw.to(self.device).unsqueeze(0)
        key_seed = self._key_seed(key)
        marked = mesh.copy()
        textured = [m for m in marked.materials if m.texture is not None]
        encoder = self.model
        if self.surface and textured and marked.uvs is not None:
            self._mark_surface(mesh, marked, message, strength)
        elif encoder.texture_encoder is not None and textured and marked.uvs is not None:
            marked = self.layout(marked, note=True)
            grid = self.mark_grid(marked)
            palette = palette_share(marked.positions, _textured_faces(marked), marked.uvs)
            if palette >= PALETTE_WARNING and warn:
                print(f"meshseal: warning: {palette:.0%} of the textured surface has faces without UV area (the "
                      "texture used as a colour palette) and could not be given charts (a tiled texture, or vertices "
                      "shared with another material): the mark has little room there and may read poorly",
                      file=sys.stderr)
            for index, material in enumerate(marked.materials):
                if material.texture is None:
                    continue
                texture = material.texture.to(self.device).permute(2, 0, 1).unsqueeze(0)
                used = texels_used(marked.uvs, marked.faces[marked.face_material == index], *texture.shape[-2:])
                try:
                    marked_texture = encoder.mark_texture(texture, message, strength, key_seed, grid, used)
                except ValueError as error:
                    raise MeshsealError(str(error)) from None
                material.texture = marked_texture[0].permute(1, 2, 0).cpu()
        elif encoder.vertex_encoder is None:
            where = f"{mesh.source.path}: " if mesh.source is not None else ""
            raise MeshsealError(f"{where}the mesh has no texture with UVs to carry the watermark, and this "
                                f"model only marks textures")
        elif encoder.texture_encoder is not None and warn:
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

    def embed_within(self, mesh: Mesh, message=None, *, bits=None, key: str | bytes | None = None,
                     strength: float = 1.0, max_flip: float = MAX_FLIP, views: int = BUDGET_VIEWS) -> tuple[Mesh, float]:
        """`embed`, then the strength lowered until the mark's mean FLIP over the object's pixels, in
        renders from `views` seeded views (256^2, our renderer: what `meshseal embed` reports), is at
        most `max_flip`: a visibility budget on top of the texture PSNR the strength sets (a texture
        minified in renders, such as a tiled brick pattern, can show a mark of 40 dB more than most).
        Never below `metrics.MIN_STRENGTH` (a warning says when the budget is not met). Returns the
        marked mesh and the strength used."""
        from .metrics import MIN_STRENGTH, seed_renders, strength_within, visibility

        if not 0.0 < max_flip <= 1.0:
            raise MeshsealError(f"max_flip must be in (0, 1], got {max_flip}")
        if views < 1:
            raise MeshsealError("a FLIP budget needs at least one view to measure it in")
        if not self.calibrated:
            raise MeshsealError("a FLIP budget is for spread-spectrum models (their strength scales the mark)")

        seen, inside = seed_renders(mesh, views)  # the original, rendered once for every try
        marked, strength, flip = strength_within(
            lambda at: self.embed(mesh, message, bits=bits, key=key, strength=at, warn=at == strength),
            lambda marked: visibility(seen, seed_renders(marked, views)[0], inside)["flip_object"], strength, max_flip)
        if flip > max_flip:
            floor = f" (the budget lowers the strength no further than {MIN_STRENGTH})" if strength <= MIN_STRENGTH else ""
            print(f"meshseal: warning: the mark's FLIP is {flip:.4f} at strength {strength:.3g}, above the budget "
                  f"{max_flip}{floor}", file=sys.stderr)
        return marked, strength

    def _mark_surface(self, mesh: Mesh, marked: Mesh, message: torch.Tensor, strength: float) -> None:
        """Each texture of `marked` (a copy of `mesh`) carrying a surface mark: its texels traced to the
        surface points they paint in the canonical frame, where the seed's cameras look from."""
        from .models.surface import texel_columns

        canonical = normalize(to_z_up(replace(mesh, source=None)))
        for index, material in enumerate(marked.materials):
            if material.texture is None:
                continue
            faces = marked.faces[marked.face_material == index]
            if len(faces) == 0:  # a texture no face uses shows nowhere
                continue
            texture = material.texture.to(self.device).permute(2, 0, 1).unsqueeze(0)
            columns, painted = texel_columns(canonical.positions, canonical.normals, faces, marked.uvs,
                                             *texture.shape[-2:])
            marked_texture = self.model.mark_texture(texture, message, strength,
                                                     columns=(columns[None].to(self.device), painted[None].to(self.device)))
            material.texture = marked_texture[0].permute(1, 2, 0).cpu()

    @property
    def surface(self) -> bool:
        """True for blind surface-code models (`models.surface`)."""
        return self.model.config.decoder == "surface"

    def _key_seed(self, key) -> int | None:
        """The keyed pattern's seed (spread-spectrum models; None for learned ones, which have no key)."""
        from . import payload

        return payload.key_seed(key) if self.calibrated else None

    @property
    def calibrated(self) -> bool:
        """True when the model's soft bits are matched-filter z-scores with a known null (a Rademacher
        sum per bit given the picture's cell evidence): detection decisions and p-values need them
        (spread-spectrum models)."""
        return self.model.config.decoder == "matched"

    def mark_grid(self, mesh: Mesh) -> int | None:
        """Cells per side of the UV square that a spread mark uses on `mesh` (coarser where its texture
        is minified, see `models.spread`); None for learned marks or a mesh without a texture and UVs."""
        if mesh.uvs is None or all(m.texture is None for m in mesh.materials):
            return None
        mesh = self.layout(mesh)
        return self.model.mark_grid(mesh.positions, _textured_faces(mesh), mesh.uvs)

    def layout(self, mesh: Mesh, note: bool = False) -> Mesh:
        """`mesh` as this model marks it, and as detection takes the original: spread-spectrum marks
        first give faces without UV area charts of their own (`mesh.charts`: a palette texture), so that
        they carry the mark too; other models take the mesh as it is. A charted mesh is its own layout,
        so `embed` of a layout charts nothing twice. `note`: say on stderr what charting added."""
        from .mesh.charts import chart_palette_faces

        charted = chart_palette_faces(mesh) if self.calibrated else mesh
        if note and charted is not mesh:
            sizes = [f"{a.texture.shape[1]}x{a.texture.shape[0]} -> {b.texture.shape[1]}x{b.texture.shape[0]}"
                     for a, b in zip(mesh.materials, charted.materials)
                     if a.texture is not None and a.texture.shape != b.texture.shape]
            print(f"meshseal: note: faces without UV area (the texture used as a colour palette) got charts of "
                  f"their own so that they carry the mark too: {charted.n_vertices - mesh.n_vertices} vertices "
                  f"added, texture {', '.join(sizes)}", file=sys.stderr)
        return charted

    # ------------------------------------------------------------ detect
    @torch.no_grad()
    def detect(self, images, mesh=None, *, key: str | bytes | None = None, expect=None, pool: bool = False,
               register: bool = False, fov_y: float = 60.0):
        """Read pictures (paths, PIL images, arrays, tensors; one or a list) of a marked mesh.

        Informed models (`informed`, the default) need the original `mesh` (a Mesh or a path): they
        take each picture's camera from its metadata (pictures from `meshseal render`) or, when it
        has none or `register` is set, find it by registration (assuming a vertical field of view
        `fov_y`), then un-render the picture onto the mesh's texture space and read the mark there.
        Blind models crop the object and decode the picture alone.

        Under `key` (None: the public key) each result says whether a mark is there at the false-
        positive rate `payload.FPR` (`detected`, `p_value`) and what it says (`message`); `expect`
        tests one known message instead (the p-value of the match). `pool` decides once for all the
        pictures (views of one asset), adding their evidence. Returns a Detection for one picture or
        for a pool, else a list.
        """
        original = self.original(mesh) if self.model.informed else None
        single = not isinstance(images, (list, tuple))
        readings = [self.look_again(self.read(image, original, register, fov_y), original, key, expect, search=not pool)
                    for image in ([images] if single else images)]
        if pool:
            results = [self.decide(readings, key, expect)]
            results[0].reason = self.why_not(results[0], original, key)
        else:
            results = [self.decide([r], key, expect) for r in readings]
            for result, reading in zip(results, readings):
                result.reason = self.why_not(result, original, key, reading)
        return results[0] if single or pool else results

    def look_again(self, reading: _Reading, original, key=None, expect=None, search: bool = True) -> _Reading:
        """A registered reading, looked at again where its mark is not found: first under the registered
        camera sharpened on the reading's own residual (`register.sharpen`: a picture whose texture
        aliases loses its mark to a tenth of a pixel of pose error), then under the registration's
        next-best views (`Registration.alternatives`: a near-symmetric shape's twin views fit its
        silhouette and texture alike, and only the keyed mark tells them apart), keeping the camera
        whose reading is likeliest marked. Where the registered camera's reading already hints at a
        mark (p-value under LOOK_AGAIN_BELOW: a twin view of a symmetric asset still reads part of the
        mark) each alternative is finished (refined on the texture) and read; else each is first read
        as refined on its silhouettes alone, and finished only where that rough reading hints at a
        mark, so that unmarked pictures pay little for it. Sharpening runs again (light refitted at the
        sharpened camera) where its first reading hints at a mark, SHARPEN_ROUNDS times at most. The
        p-value pays for all of it (Bonferroni over three stages, each given a third: the registered
        camera, the sharpened ones, the alternatives): x3 at the registered camera, x3R at a sharpened
        one of R rounds, x3K at the best of K alternatives (x2 and x2R without alternatives), so that a
        reading's p-value stays valid however the camera was picked (rough readings only decide what
        to finish). Other readings, and all of them with `search` False (pooling), come back as they
        are, without what a second look needs."""
        from . import payload
        from .register import sharpen, silhouette_iou

        if not reading.second_look:
            return reading
        picture, mask, alternatives = reading.second_look
        if not search or not self.calibrated:
            return replace(reading, second_look=())
        stages = 3 if alternatives else 2
        first = replace(reading, second_look=(), tries=stages)
        decision = self.decide([first], key, expect)
        if decision.detected:
            return first
        hinted = decision.p_value <= LOOK_AGAIN_BELOW
        best, best_p = first, decision.p_value

        on_cpu, on_device = self._on_cpu(original), picture.to(self.device)

        def under(camera, tries: int) -> tuple[_Reading, float]:
            camera = camera.to(self.device)
            other = replace(first, evidence=self._evidence(original, on_device, camera), found=camera, tries=tries)
            return other, self.decide([other], key, expect).p_value

        camera = reading.found.to("cpu")
        for _ in range(SHARPEN_ROUNDS):  # each round refits the light at the camera the last one found
            camera = sharpen(on_cpu, camera, picture, mask[None].float())
            sharpened, p_value = under(camera, stages * SHARPEN_ROUNDS)
            if p_value < best_p:
                best, best_p = sharpened, p_value
            if payload.detected(p_value) or p_value > LOOK_AGAIN_BELOW:
                break
        for alternative in alternatives:
            if payload.detected(best_p):
                break  # every stage is paid for, tried or not
            if not (hinted or alternative.finished):
                rough = replace(first, evidence=self._evidence(original, on_device, alternative.rough().to(self.device)))
                if self.decide([rough], key, expect).p_value > LOOK_AGAIN_BELOW:
                    continue
            other, p_value = under(alternative.finish(), stages * len(alternatives))
            if p_value < best_p:
                best, best_p = other, p_value
        # Only the kept camera's silhouette overlap is reported: the others are never rendered for it.
        return best if best is first else replace(best, registration_iou=silhouette_iou(on_cpu, best.found.to("cpu"), mask))

    def decide(self, readings: list[_Reading], key=None, expect=None) -> Detection:
        """The decision on the evidence of `read` (several readings: pooled, their evidence added)."""
        from . import payload

        first = readings[0]
        extra = {"box": first.box if len(readings) == 1 else None, "camera": first.camera,
                 "registration_iou": first.registration_iou if len(readings) == 1 else None,
                 "pictures": len(readings),
                 "silhouette_iou": first.registration_iou if len(readings) == 1 else None}
        evidence = torch.stack([r.evidence for r in readings]).sum(0, keepdim=True)
        weights, tries = None, 1
        expected = payload.encode(expect, key, self.n_bits) if expect is not None and self.n_bits in payload.SCHEMAS else None
        if self.calibrated:
            soft, weights, tries = self._best_grid(evidence, key, expected)
            tries *= math.prod(r.tries for r in readings)  # the cameras second looks could try (`look_again`)
        else:
            soft = evidence[0].double()
        bits = "".join("1" if v > 0 else "0" for v in soft.tolist())
        if self.n_bits not in payload.SCHEMAS:
            return Detection(bits, soft.tolist(), None, None, None, None, **extra)
        # Each grid read is one more try at the false-positive rate: its p-value pays for all (Bonferroni).
        any_mark_p = min(1.0, tries * float(payload.detection_pvalue(soft, weights))) if self.calibrated else None
        marked = any_mark_p is not None and payload.detected(any_mark_p)
        decoded = payload.decode(soft, key) if marked or expect is not None else None  # no message to report else
        if expect is not None:
            if self.calibrated:
                p_value = min(1.0, tries * float(payload.match_pvalue(soft, expected, weights)))
            else:
                p_value = payload.binomial_pvalue(int(((soft > 0).float() == expected).sum()), self.n_bits)
            # A mark of another message still correlates with this one: the code must read this one.
            detected = payload.detected(p_value) and decoded.message == _plain(expect)
        elif self.calibrated:
            p_value, detected = any_mark_p, marked
        else:  # uncalibrated logits: no decision without an expected message
            p_value, detected = None, None
        message = decoded.message if detected or marked else None
        return Detection(bits, soft.tolist(), p_value, detected, message,
                         decoded.errors_corrected if message is not None else None, **extra)

    def _best_grid(self, evidence: torch.Tensor, key, expected) -> tuple[torch.Tensor, torch.Tensor, int]:
        """Soft bits and cell weights of the cell grid (of those `read` put side by side) whose mark is
        likeliest, and the number of grids tried. The pick is by the statistic the p-value grows with
        (sum of z^2; with an `expected` message, its correlation with the message's signs), so only the
        picked grid pays for an exact p-value; any rule of picking keeps `decide`'s Bonferroni bound."""
        from .models.spread import bit_weights, soft_bits, split_grids

        encoder, key_seed = self.model.texture_encoder, self._key_seed(key)
        parts = split_grids(encoder, evidence)
        softs = [soft_bits(encoder, sums, key_seed)[0].double() for sums in parts]
        if expected is None:
            scores = [float((soft * soft).sum()) for soft in softs]
        else:
            scores = [float((soft * (2.0 * expected.to(soft) - 1.0)).sum()) for soft in softs]
        best = max(range(len(parts)), key=scores.__getitem__)
        return softs[best], bit_weights(encoder, parts[best], key_seed)[0].double(), len(parts)

    def why_not(self, result: Detection, original, key=None, reading: _Reading | None = None) -> str | None:
        """Why a picture read no mark, where a plausible mistake explains it, else None: the mesh
        given as the original is itself marked under `key` (`own_mark_pvalue` under the FPR: a
        picture of it then reads nothing against it), or the picture's object does not match the
        original's silhouette under the picture's camera (IoU under SHOWS_MESH_BELOW: another mesh,
        or a registration gone astray). A mark made under another key is not told apart from no mark
        (docs/payload.md). A picture whose camera came from its metadata gets its silhouette IoU
        here (`result.silhouette_iou`), from its `reading`, only when it read no mark."""
        from . import payload

        if result.detected is not False or result.message is not None or original is None:
            return None  # (a message read, but not the one --expect names: no mistake to explain)
        if result.silhouette_iou is None and reading is not None and reading.object_mask is not None:
            from .register import silhouette_iou

            result.silhouette_iou = silhouette_iou(self._on_cpu(original), reading.found.to("cpu"), reading.object_mask)
        key_seed = self._key_seed(key)
        if self._own_of is None or self._own_of[0] is not original or self._own_of[1] != key_seed:
            self._own_of = (original, key_seed, self.own_mark_pvalue(original, key))
        own = self._own_of[2]
        if own is not None and payload.detected(own):
            return (f"the mesh given as the original is itself marked under this key (p = {own:.2g}): "
                    f"give the unmarked original with --mesh")
        if result.silhouette_iou is not None and result.silhouette_iou < SHOWS_MESH_BELOW:
            return f"the picture does not seem to show this mesh (silhouette IoU {result.silhouette_iou:.2f})"
        return None

    def own_mark_pvalue(self, original, key=None) -> float | None:
        """The p-value that the textures of `original` (from `original()`) carry a mark under `key`
        themselves, read from the textures alone (`models.spread.texture_cell_sums`, every grid
        detection reads, their sums over the materials, Bonferroni over the grids): under FPR, the
        mesh given as the original is a marked copy, against which a picture of it reads no mark.
        None for models without calibrated soft bits."""
        from . import payload
        from .models.spread import bit_weights, soft_bits, split_grids, texture_cell_sums

        if not self.calibrated:
            return None
        encoder, key_seed = self.model.texture_encoder, self._key_seed(key)
        grids = self._grids_to_read(original)
        faces = original.faces[0] if original.faces.dim() == 3 else original.faces
        material = original.face_material[0] if original.face_material.dim() == 2 else original.face_material
        total = None
        for index, texture in enumerate(original.textures):
            if texture is None:
                continue
            texture = texture[None] if texture.dim() == 3 else texture[:1]  # (1, 3, H, W)
            used = texels_used(original.uvs[0], faces[material == index], *texture.shape[-2:])
            sums = texture_cell_sums(encoder, texture, used, grids)
            total = sums if total is None else total + sums
        if total is None:
            return None
        parts = split_grids(encoder, total.cpu())
        p_values = [float(payload.detection_pvalue(soft_bits(encoder, sums, key_seed)[0].double(),
                                                   bit_weights(encoder, sums, key_seed)[0].double())) for sums in parts]
        return min(1.0, len(parts) * min(p_values))

    @property
    def informed(self) -> bool:
        """True when detection needs the original mesh."""
        return self.model.informed

    def original(self, mesh):
        """The original mesh (a Mesh, a path, or an already prepared MeshBatch) in the canonical frame,
        ready for informed detection; prepare it once to detect many pictures of it."""
        from .mesh import load as load_mesh
        from .render import MeshBatch

        if isinstance(mesh, MeshBatch):
            return mesh
        if mesh is None:
            raise MeshsealError("this model reads pictures with the original mesh: give it (--mesh FILE)")
        if isinstance(mesh, (str, Path)):
            mesh = load_mesh(mesh)
        if mesh.uvs is None or all(m.texture is None for m in mesh.materials):
            raise MeshsealError("the original mesh has no texture with UVs, so it cannot carry this model's mark")
        return MeshBatch.from_mesh(normalize(to_z_up(replace(self.layout(mesh), source=None))).to(self.device))

    def read(self, image, original, register: bool = False, fov_y: float = 60.0, camera=None) -> _Reading:
        """One picture's evidence, before any decision (`decide`); `original` from `original()`, None
        for blind models. `camera` (one `Cameras`, canonical frame) overrides metadata and registration
        (experiments comparing with the true camera). A batch reads each picture on its own and keeps
        going past bad ones."""
        pixels, alpha, camera_text = _load_image(image)
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
            mask, background = object_mask(pixels, trim=not (given or from_metadata))
        if int(mask.sum()) < MIN_OBJECT_PIXELS:  # answer at once rather than search an empty picture
            what = "transparent, or nearly" if alpha is not None else "one plain colour, or nearly"
            raise MeshsealError(f"{_name(image)}: no object found (the picture is {what})")
        tensor = torch.from_numpy(np.ascontiguousarray(pixels)).permute(2, 0, 1)[None].to(self.device)
        if from_metadata:
            camera = _camera_from_metadata(camera_text, self.device, _name(image))
        source, iou = None, None
        if camera is not None:  # the known camera says where the object is: no need to search for it
            from .render import clip_to_screen

            height, width = pixels.shape[:2]
            corners = clip_to_screen(camera.world_to_clip(original.positions, width / height), height, width)
            box = box_from_points(corners.reshape(-1, 2), height, width)
            evidence, source = self._evidence(original, tensor.clamp(0, 1), camera), "given" if given else "metadata"
            if from_metadata:  # kept for `why_not`: does the picture show this mesh where its camera says?
                return _Reading(evidence, tuple(float(v) for v in box[0]), source, iou, camera,
                                object_mask=torch.from_numpy(np.ascontiguousarray(mask > 0.5)))
        else:
            box = boxes_from_mask(torch.from_numpy(mask)[None])
            background_tensor = torch.tensor(background, dtype=tensor.dtype)[None].to(self.device)
            if original is None and self.surface:
                from .models.surface import read_picture

                evidence = read_picture(self.model.texture_encoder, pixels.clip(0, 1), mask > 0.5)
            elif original is None:
                framed = crop_boxes(tensor, box, self.model.config.frame_size, background_tensor)
                evidence = self.model.decode(framed.clamp(0, 1))[0].cpu()
            else:
                from .register import register_with_masks

                guesses, recut = self._object_guesses(pixels, mask, alpha, original)
                with torch.enable_grad():
                    found = register_with_masks(self._on_cpu(original), tensor[0].cpu(), guesses,
                                                background_tensor[0].cpu(), fov_y=fov_y, recut=recut)
                box = found.box[None]
                source, iou, camera = "registered", found.iou, found.camera.to(self.device)
                evidence = self._evidence(original, tensor.clamp(0, 1), camera)
                second_look = (tensor.clamp(0, 1).cpu(), torch.from_numpy(np.ascontiguousarray(mask)), found.alternatives)
                return _Reading(evidence, tuple(float(v) for v in box[0]), source, iou, camera, second_look=second_look)
        return _Reading(evidence, tuple(float(v) for v in box[0]), source, iou, camera)

    def _object_guesses(self, pixels: np.ndarray, mask: np.ndarray, alpha, original):
        """The object's pixels as registration should try them, and how to cut them again from a
        registered silhouette (None where the picture's alpha channel gives them): the plain-background
        `mask`, and where the background is busy (`segment.busy_background`) a cut guided by the
        original's colours too, first, unless the two agree; `segment.recut` of the picture (a dark
        object on a dark backdrop loses parts of it to the plain-background mask, too)."""
        from .segment import GUESSES_AGREE, busy_background, guided_object_mask, mask_iou, recut

        guesses = [mask]
        if alpha is None and busy_background(pixels):
            guided = guided_object_mask(pixels, self._on_cpu(original))
            if int(guided.sum()) >= MIN_OBJECT_PIXELS and mask_iou(guided, mask) < GUESSES_AGREE:
                guesses.insert(0, guided)
        again = None if alpha is not None else (lambda silhouette: recut(pixels, silhouette))
        return [torch.from_numpy(np.ascontiguousarray(g)) for g in guesses], again

    def _on_cpu(self, original):
        """The prepared original on the CPU, where registration runs whatever the model's device (its
        many small Gauss-Newton steps are written and tested for the CPU); kept for the next picture."""
        if original.positions.device.type == "cpu":
            return original
        if self._cpu_of is None or self._cpu_of[0] is not original:
            self._cpu_of = (original, original.to("cpu"))
        return self._cpu_of[1]

    def _evidence(self, original, picture: torch.Tensor, camera) -> torch.Tensor:
        """Matched-filter cell sums (spread models) or decoder logits of one picture (1, 3, H, W)."""
        from .pipeline import read_bits, spread_evidence

        if self.calibrated:  # every grid a mark may use on this mesh, side by side (`decide` splits them)
            return spread_evidence(self.model, original, picture, camera, grids=self._grids_to_read(original))[0].cpu()
        return read_bits(self.model, original, picture, camera)[0].cpu()

    def _grids_to_read(self, original) -> tuple[int, ...]:
        """`grids_to_read` of a prepared original, worked out once for it rather than per picture (it
        measures every face: ~5 ms on a 4k-face mesh, and a folder holds many pictures of one asset)."""
        encoder = self.model.texture_encoder
        if self._grids_of is None or self._grids_of[0] is not original or self._grids_of[1] is not encoder:
            self._grids_of = (original, encoder, encoder.grids_to_read(*_textured_geometry(original)))
        return self._grids_of[2]


def _textured_geometry(batch) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Positions, textured faces and uvs of a prepared original (a one-mesh MeshBatch)."""
    faces = batch.faces[0] if batch.faces.dim() == 3 else batch.faces
    material = batch.face_material[0] if batch.face_material.dim() == 2 else batch.face_material
    textured = torch.tensor([t is not None for t in batch.textures], device=material.device)
    return batch.positions[0], faces[textured[material.long()]], batch.uvs[0]


def _textured_faces(mesh) -> torch.Tensor:
    """The faces (F', 3) of a Mesh whose material has a texture (the ones a texture mark lies on)."""
    textured = torch.tensor([m.texture is not None for m in mesh.materials])
    if mesh.face_material is None:
        return mesh.faces if bool(textured.any()) else mesh.faces[:0]
    return mesh.faces[textured[mesh.face_material.long()]]


def _camera_from_metadata(text: str, device, name: str = "picture"):
    """The camera a `meshseal render` picture carries in its PNG text chunk."""
    import json

    from .mesh.io import camera_from_dict

    try:
        return camera_from_dict(json.loads(text)).to(device)
    except (ValueError, RecursionError):
        raise MeshsealError(f"{name}: the picture's camera metadata is not valid JSON") from None
    except MeshsealError as error:
        raise MeshsealError(f"{name}: {error}") from None


def _plain(message):
    """What `payload.decode` returns for a message given to `encode` (a Message's value, else itself)."""
    return getattr(message, "value", message)


def load(model: str | None = None, device: str | None = None) -> Watermarker:
    """Load a shipped model by name (default: 'default') or a checkpoint path (.safetensors)."""
    path = resolve_model(model)
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    return Watermarker(load_model(path, device), path.stem)


__all__ = ["load", "Watermarker", "Detection", "shipped_models", "parse_bits"]
