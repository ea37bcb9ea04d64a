"""The one interface every watermarking scheme implements, and the decision all of them share.

A `Method` wraps a `models.WatermarkModel` (its buffers and networks) and answers what `Watermarker`
and the training pass ask of a scheme:

- `layout(mesh)`: the mesh as the scheme marks it, and as detection takes the original;
- `embed(mesh, message, key_seed, strength, warn)`: a marked copy of the mesh;
- `prepare(mesh)`: the original ready for reading (informed schemes), once for many pictures;
- `evidence(original, picture, camera)` (informed) or `blind_evidence(pixels, mask, background)`
  (blind): one picture's evidence, before any decision;
- `soft_bits(evidence, key, expected)`: soft bits, their null weights and the grids tried;
- `decide(readings, key, expect)`: the Detection (shared here: it needs only `soft_bits`);
- `mark_batch` / `read_batch`: the same two halves on a training batch (`training.step.run_pass`).

Capabilities are attributes, not kinds: `informed` (reading needs the original mesh and the
picture's camera), `calibrated` (soft bits are z-scores with an exact null, so decisions and
p-values exist), `takes_strength` (the mark's amplitude is a free knob), `flip_budget` (embedding keeps the mark
within a visibility budget by default), `second_look` (a registered
reading may be looked at again, `reading.second_look`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .. import payload


@dataclass
class Detection:
    """What detection read from one picture (or, pooled, from several pictures of one asset).

    detected: whether the picture carries a mark under the key, at the false-positive rate
    `payload.FPR` (None for methods without calibrated soft bits); p_value: the chance that a picture
    without such a mark scores this high (see payload.detection_pvalue / match_pvalue); message: the
    decoded text or ID, None when not detected or not decodable; bits: the raw hard bits '0101...';
    soft: the soft bits (matched-filter z, mean 0 and variance 1 each without a mark; learned models:
    logits); errors_corrected: raw bits the error correction flipped. `box` is the object's square box
    (cx, cy, half) in the picture; `camera` 'metadata' or 'registered' for informed methods.
    `silhouette_iou`: the original's silhouette under the picture's camera against the picture's
    object (registered pictures; pictures whose camera came from metadata when they read no mark);
    `reason`: why no mark was read, where a plausible mistake explains it (`Watermarker.why_not`).
    `list_only`: tested against a list of messages and detected, whether the message is the list's
    best match alone (True: the code could not read it, so a message outside the list is not ruled
    out) or the code read it too (False); None otherwise. `named`: tested against an expected message
    (or a list), whether the match named it; a model with a pilot may detect a mark (its pilot's
    p-value) that the match does not name: detected, named False. None without an expected message.
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
    list_only: bool | None = None
    named: bool | None = None

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
        if self.list_only is not None:
            result["list_only"] = self.list_only
        if self.named is not None:
            result["named"] = self.named
        return result


class Method:
    """A watermarking scheme over a `WatermarkModel` (see the module docstring for the protocol)."""

    name = "method"
    informed = False
    calibrated = False
    takes_strength = False
    flip_budget = False  # `meshseal embed` keeps the mark within a FLIP budget by default (`Watermarker.embed_within`)
    second_look = False
    paper_pictures = False  # evaluated on the paper's 600 x 400 pictures by default

    def __init__(self, model):
        self.model = model

    @property
    def n_bits(self) -> int:
        return self.model.n_bits

    @property
    def device(self) -> torch.device:
        return self.model.device

    params_named: tuple[str, ...] = ()  # the config fields this scheme uses (empty: all of them)

    def params(self) -> dict:
        """The scheme's parameters as a model card names them: the config fields it uses."""
        config = self.model.config.to_dict()
        return {k: v for k, v in config.items() if not self.params_named or k in self.params_named}

    # ------------------------------------------------------------ embed
    def layout(self, mesh, note: bool = False):
        """`mesh` as this method marks it and as detection takes the original (default: as it is)."""
        return mesh

    def mark_grid(self, mesh) -> int | None:
        """The cell grid the mark uses on `mesh` (None: the method has no grid)."""
        return None

    def embed(self, mesh, message: torch.Tensor, key_seed: int | None, strength: float, warn: bool):
        """A marked copy of `mesh` carrying `message` (1, N) in {0, 1}."""
        raise NotImplementedError

    def key_seed(self, key) -> int | None:
        """The keyed pattern's seed (None for methods whose pattern has no key)."""
        return None

    # ------------------------------------------------------------ read
    def prepare(self, mesh):
        """The original, ready for reading many pictures of it (informed methods)."""
        raise NotImplementedError(f"the {self.name} method reads pictures without the original mesh")

    def evidence(self, original, picture: torch.Tensor, camera) -> torch.Tensor:
        """One picture (1, 3, H, W) seen from `camera` -> its evidence (E,) (informed methods)."""
        raise NotImplementedError(f"the {self.name} method reads pictures without the original mesh")

    def read_pictures(self, original, pictures: torch.Tensor, cameras, key_seed: int | None = None) -> torch.Tensor:
        """Soft bits (B, N) of pictures (B, 3, H, W) of a prepared original seen from `cameras` (informed methods)."""
        raise NotImplementedError(f"the {self.name} method reads pictures without the original mesh")

    def blind_evidence(self, pixels, mask, background: torch.Tensor) -> torch.Tensor:
        """One picture (H, W, 3) numpy in [0, 1] with its object `mask` -> its evidence (E,) (blind methods)."""
        raise NotImplementedError(f"the {self.name} method reads pictures with the original mesh")

    def soft_bits(self, evidence: torch.Tensor, key, expected) -> tuple[torch.Tensor, torch.Tensor | None, int]:
        """Pooled evidence (1, E) -> soft bits (N,) double, their null weights (None: not
        calibrated) and how many readings were tried to pick them (the p-value pays for each)."""
        return evidence[0].double(), None, 1

    def own_mark_pvalue(self, original, key=None) -> float | None:
        """The p-value that the original's own textures carry a mark under `key` (None: not measurable)."""
        return None

    def pilot_pvalue(self, evidence: torch.Tensor, key) -> float | None:
        """Pooled evidence (1, E) -> the exact p-value of the matched filter over the pilot's cells (the
        key's own signs: a presence test whatever the message), the grids tried paid for. None where
        the method's mark has no pilot."""
        return None

    def decide(self, readings: list, key=None, expect=None) -> Detection:
        """The decision on the evidence of readings (`reading.read.Reading`; several: pooled, their
        evidence added). Each reading's `tries` (cameras a second look could try) multiplies the
        p-value, as does every grid `soft_bits` tried (Bonferroni)."""
        first = readings[0]
        single = len(readings) == 1
        extra = {"box": first.box if single else None, "camera": first.camera,
                 "registration_iou": first.registration_iou if single else None,
                 "pictures": len(readings), "silhouette_iou": first.registration_iou if single else None}
        evidence = torch.stack([r.evidence for r in readings]).sum(0, keepdim=True)
        coded = self.n_bits in payload.SCHEMAS
        among = isinstance(expect, (list, tuple))  # the owner's list of messages: which of them, if any
        expected = None
        if expect is not None and coded:
            expected = payload.encode_many(expect, key, self.n_bits) if among else payload.encode(expect, key, self.n_bits)
        soft, weights, tries = self.soft_bits(evidence, key, expected)
        tries *= math.prod(r.tries for r in readings)
        bits = "".join("1" if v > 0 else "0" for v in soft.tolist())
        if not coded:
            return Detection(bits, soft.tolist(), None, None, None, None, **extra)
        calibrated = weights is not None
        any_mark_p = min(1.0, tries * float(payload.detection_pvalue(soft, weights))) if calibrated else None
        looks = math.prod(r.tries for r in readings)  # the cameras a second look tried
        pilot = self.pilot_pvalue(evidence, key) if calibrated else None
        if pilot is not None:  # the pilot's test beside the bits', a weighted Bonferroni over the two
            any_mark_p = payload.any_mark_pvalue(any_mark_p, min(1.0, looks * pilot))
        marked = any_mark_p is not None and payload.detected(any_mark_p)
        # No message to report else. The soft decoding models z-scores (unit noise): logits of a learned
        # decoder have no such scale, so theirs is the hard decoding alone.
        decoded = payload.decode(soft, key, soft_retry=calibrated) if marked or expect is not None else None
        if expect is not None:
            named, family = expect, 1
            # The message's own cells alone, not the pilot's: they would find any message of a mark there.
            if among:  # the message of the list that the soft bits agree with best, paid for by the list's length
                best = int(((2.0 * expected.double() - 1.0) @ soft.double()).argmax())
                named, family, expected = expect[best], len(expect), expected[best]
            if calibrated:
                p_value = min(1.0, tries * family * float(payload.match_pvalue(soft, expected, weights)))
            else:
                p_value = min(1.0, family * payload.binomial_pvalue(int(((soft > 0).float() == expected).sum()), self.n_bits))
            # The match tests "no mark under this key" (its p-value is exact under that null whatever
            # the code reads), so a mark too weak for the code to decode is still found. A mark of
            # another message also correlates with this one: where the code reads another message, no.
            detected = payload.detected(p_value) and decoded.message in (None, getattr(named, "value", named))
            if among and detected:  # the list names the message even where the code alone cannot read it
                message = getattr(named, "value", named)
                flipped = int(((soft > 0).double() != expected.double()).sum())
                return Detection(bits, soft.tolist(), p_value, True, message, flipped, **extra,
                                 list_only=decoded.message is None, named=True)
            if not detected and pilot is not None and marked:
                # The pilot finds a mark whatever its message, where the message's own cells do not
                # confirm the one expected: detected at the FPR, the message not named.
                return Detection(bits, soft.tolist(), any_mark_p, True, decoded.message,
                                 decoded.errors_corrected if decoded.message is not None else None, **extra,
                                 named=False)
            extra["named"] = bool(detected)
        elif calibrated:
            p_value, detected = any_mark_p, marked
        else:  # uncalibrated logits: no decision without an expected message
            p_value, detected = None, None
        message = decoded.message if detected or marked else None
        return Detection(bits, soft.tolist(), p_value, detected, message,
                         decoded.errors_corrected if message is not None else None, **extra)

    # ------------------------------------------------------------ training pass
    def mark_batch(self, batch: dict, message: torch.Tensor, vertex_mask):
        """A dataset batch marked: (normals, uvs, texture, shown texels (B, 1, H, W) or None)."""
        raise NotImplementedError

    def read_batch(self, pictures, alpha, original_mesh, cameras, original_image, background, frame_size,
                   distortions_2d, generator, reference_mix):
        """What the pass decodes: (decoder input, logits or soft bits (B, N))."""
        raise NotImplementedError


def source_prefix(mesh) -> str:
    """'path: ' of the file a mesh came from, for error messages ('' for a mesh made in memory)."""
    return f"{mesh.source.path}: " if mesh.source is not None else ""


def informed_original(method: Method, mesh):
    """The original mesh (a Mesh, a path, or an already prepared MeshBatch) in the canonical frame, laid
    out as `method` marks it, on its device: what informed reading un-renders pictures onto."""
    from dataclasses import replace
    from pathlib import Path

    from ..errors import MeshsealError
    from ..mesh import load as load_mesh
    from ..mesh import normalize, to_z_up
    from ..render import MeshBatch

    if isinstance(mesh, MeshBatch):
        return mesh
    if mesh is None:
        raise MeshsealError("this model reads pictures with the original mesh: give it (--mesh FILE)")
    if isinstance(mesh, (str, Path)):
        mesh = load_mesh(mesh, cache=True)  # read only: the load cache skips trimesh for a mesh met before
    if mesh.uvs is None or all(m.texture is None for m in mesh.materials):
        raise MeshsealError("the original mesh has no texture with UVs, so it cannot carry this model's mark")
    return MeshBatch.from_mesh(normalize(to_z_up(replace(method.layout(mesh), source=None))).to(method.device))


def textured_geometry(batch) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Positions, textured faces and uvs of a prepared original (a one-mesh MeshBatch)."""
    faces = batch.faces[0] if batch.faces.dim() == 3 else batch.faces
    material = batch.face_material[0] if batch.face_material.dim() == 2 else batch.face_material
    textured = torch.tensor([t is not None for t in batch.textures], device=material.device)
    return batch.positions[0], faces[textured[material.long()]], batch.uvs[0]


def textured_faces(mesh) -> torch.Tensor:
    """The faces (F', 3) of a Mesh whose material has a texture (the ones a texture mark lies on)."""
    textured = torch.tensor([m.texture is not None for m in mesh.materials])
    if mesh.face_material is None:
        return mesh.faces if bool(textured.any()) else mesh.faces[:0]
    return mesh.faces[textured[mesh.face_material.long()]]
