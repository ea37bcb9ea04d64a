"""The public API: `wm = meshseal.load(); marked = wm.embed(mesh, "ab42"); result = wm.detect(picture, mesh)`.

`Watermarker` is a facade over one `methods.Method` (the scheme) and a `reading.read.Reader` (pictures in,
camera from metadata or registration, a second look): it parses messages and keys, applies a
visibility budget, and explains a picture that reads no mark."""

from __future__ import annotations

import sys

import torch

from .errors import MeshsealError
from .evaluation.metrics import BUDGET_VIEWS, MAX_FLIP
from .mesh import Mesh
from .methods import Detection, method_for
from .models import WatermarkModel
from .models.io import load_model
from .reading.read import Reader, Reading
from .reading.second_look import look_again

from .shipped import WEIGHTS_DIR, resolve_model
SHOWS_MESH_BELOW = 0.8  # `why_not`: an object overlapping the original's silhouette less than this may be another mesh
# `why_not`: the default's marks made before its pilot took blocks of cells are the `cell_pilot` model's, those
# made before it took a pilot the `dense` model's, and those made before it moved to 64^2 cells (f70e3d2) the
# `fine` model's; a picture the default reads nothing in is read again by each under the same camera, in this
# order. What each note says of the model.
PREVIOUS_DEFAULTS = {"cell_pilot": "the default before its pilot took blocks of cells",
                     "dense": "the default before it took a pilot", "fine": "the default before it moved to 64^2 cells"}


def shipped_models() -> list[dict]:
    """The models inside the package: name, raw bits, method, payload bits (after error correction and
    header; None without a payload schema), strategy, whether detection needs the original mesh
    (informed) and whether its soft bits are calibrated z-scores (p-values, decisions), path."""
    from .payload import SCHEMAS, payload_bits

    models = []
    for path in sorted(WEIGHTS_DIR.glob("*.safetensors")):
        model = load_model(path, "cpu")
        method, n_bits = method_for(model), model.n_bits
        models.append({"name": path.stem, "n_bits": n_bits, "method": method.name,
                       "payload_bits": payload_bits(n_bits) if n_bits in SCHEMAS else None,
                       "strategy": model.config.strategy, "informed": method.informed,
                       "calibrated": method.calibrated, "path": str(path)})
    return models


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


class Watermarker:
    """A model and the operations users need: `embed`, `embed_within`, `detect`."""

    def __init__(self, model: WatermarkModel, name: str = "custom"):
        self.model = model.eval()
        self.name = name
        self.method = method_for(self.model)
        self.reader = Reader(self.method)
        self._own_of: tuple | None = None  # (prepared original, key seed, own_mark_pvalue) for `why_not`
        self._previous: dict = {}  # PREVIOUS_DEFAULTS' Watermarkers, each loaded when `why_not` first needs it

    @property
    def n_bits(self) -> int:
        return self.model.n_bits

    @property
    def device(self) -> torch.device:
        return self.model.device

    @property
    def informed(self) -> bool:
        """True when detection needs the original mesh."""
        return self.method.informed

    # ------------------------------------------------------------ embed
    @torch.no_grad()
    def embed(self, mesh: Mesh, message=None, *, bits=None, key: str | bytes | None = None,
              strength: float = 1.0, warn: bool = True) -> Mesh:
        """A copy of `mesh` carrying `message` (text, an int ID or a `payload.Message`; error-corrected
        and keyed, see `payload`) or raw `bits` ('0101...' or a sequence of 0/1 of the model's length,
        no error correction). `key` (None: the public key) keys both the payload and the mark's pattern.
        `strength` scales a method's default amplitude where it has one (2: 6 dB louder and more
        robust; 0.5: quieter). `warn`: print warnings about the mesh to stderr. Positions never
        change; what else may (added charts for faces without UV area, normals) is the method's."""
        from . import payload

        if not 0.0 < strength <= 10.0:
            raise MeshsealError(f"strength must be in (0, 10], got {strength}")
        if (message is None) == (bits is None):
            raise MeshsealError("give either a message or raw bits")
        if bits is None and isinstance(message, (list, tuple, torch.Tensor)):
            bits, message = message, None  # a sequence of 0/1 is raw bits
        raw = parse_bits(bits, self.n_bits) if bits is not None else payload.encode(message, key, self.n_bits)
        return self.method.embed(mesh, raw.to(self.device).unsqueeze(0), self.method.key_seed(key), strength, warn)

    def embed_within(self, mesh: Mesh, message=None, *, bits=None, key: str | bytes | None = None,
                     strength: float = 1.0, max_flip: float = MAX_FLIP, views: int = BUDGET_VIEWS) -> tuple[Mesh, float]:
        """`embed`, then the strength lowered until the mark's mean FLIP over the object's pixels, in
        renders from `views` seeded views (256^2, our renderer: what `meshseal embed` reports), is at
        most `max_flip`: a visibility budget on top of the texture PSNR the strength sets (a texture
        minified in renders, such as a tiled brick pattern, can show a mark far more than most).
        Never below `evaluation.metrics.MIN_STRENGTH` (a warning says when the budget is not met).
        Returns the marked mesh and the strength used."""
        from .evaluation.metrics import MIN_STRENGTH, seed_renders, strength_within, visibility

        if not 0.0 < max_flip <= 1.0:
            raise MeshsealError(f"max_flip must be in (0, 1], got {max_flip}")
        if views < 1:
            raise MeshsealError("a FLIP budget needs at least one view to measure it in")
        if not self.method.flip_budget:
            raise MeshsealError(f"a FLIP budget is for spread-spectrum models (their strength scales the mark), "
                                f"not the {self.method.name} method")

        seen, inside = seed_renders(mesh, views)  # the original, rendered once for every try
        marked, strength, flip = strength_within(
            lambda at: self.embed(mesh, message, bits=bits, key=key, strength=at, warn=at == strength),
            lambda marked: visibility(seen, seed_renders(marked, views)[0], inside)["flip_object"], strength, max_flip)
        if flip > max_flip:
            floor = f" (the budget lowers the strength no further than {MIN_STRENGTH})" if strength <= MIN_STRENGTH else ""
            print(f"meshseal: warning: the mark's FLIP is {flip:.4f} at strength {strength:.3g}, above the budget "
                  f"{max_flip}{floor}", file=sys.stderr)
        return marked, strength

    def embed_loudest(self, mesh: Mesh, message=None, *, bits=None, key: str | bytes | None = None,
                      max_flip: float = MAX_FLIP, min_psnr: float | None = None,
                      views: int = BUDGET_VIEWS) -> tuple[Mesh, float]:
        """`embed` at the loudest strength that the visibility budgets of the object's renders allow: a
        mean FLIP over the object's pixels of at most `max_flip` and an object PSNR of at least
        `min_psnr` (None: `evaluation.metrics.MIN_OBJECT_PSNR`), in renders from `views` seeded views
        (256^2, our renderer, as `embed_within` measures), between `evaluation.metrics.MIN_STRENGTH` and
        `MAX_STRENGTH` (`strength_filled`). A louder mark survives more of a picture's road to the web
        (JPEG, WebP, resizing: docs/mark.md, "Strength against the web"); the texture's own PSNR then
        falls under the default's 40 dB wherever the renders leave room. Returns the marked mesh and the
        strength used."""
        from .evaluation.metrics import MIN_OBJECT_PSNR, seed_renders, strength_filled, visibility

        min_psnr = MIN_OBJECT_PSNR if min_psnr is None else min_psnr
        if not 0.0 < max_flip <= 1.0:
            raise MeshsealError(f"max_flip must be in (0, 1], got {max_flip}")
        if views < 1:
            raise MeshsealError("the loudest strength is measured in renders: give at least one view")
        if not self.method.flip_budget:
            raise MeshsealError(f"the loudest strength is for spread-spectrum models (their strength scales the mark), "
                                f"not the {self.method.name} method")
        seen, inside = seed_renders(mesh, views)  # the original, rendered once for every try
        marked, strength, flip, psnr = strength_filled(
            lambda at: self.embed(mesh, message, bits=bits, key=key, strength=at, warn=at == 1.0),
            lambda marked: visibility(seen, seed_renders(marked, views)[0], inside), max_flip, min_psnr)
        if flip > max_flip or psnr < min_psnr:
            print(f"meshseal: warning: the mark's FLIP is {flip:.4f} and its object PSNR {psnr:.2f} dB at strength "
                  f"{strength:.3g}, outside the budgets (FLIP {max_flip}, {min_psnr:g} dB)", file=sys.stderr)
        return marked, strength

    def layout(self, mesh: Mesh, note: bool = False) -> Mesh:
        """`mesh` as this model marks it, and as detection takes the original (`Method.layout`)."""
        return self.method.layout(mesh, note)

    def mark_grid(self, mesh: Mesh) -> int | None:
        """Cells per side of the UV square the mark uses on `mesh` (None: the method has no grid)."""
        return self.method.mark_grid(mesh)

    # ------------------------------------------------------------ detect
    # Reading runs under inference mode: no gradient flows, and torch then skips the version counters
    # and view tracking of every one of a reading's thousands of small operations.
    @torch.inference_mode()
    def detect(self, images, mesh=None, *, key: str | bytes | None = None, expect=None, pool: bool = False,
               register: bool = False, fov_y: float = 60.0, quick: bool = False):
        """Read pictures (paths, PIL images, arrays, tensors; one or a list) of a marked mesh.

        Informed methods (the default) need the original `mesh` (a Mesh, a path, or `original()`'s
        result): they take each picture's camera from its metadata (pictures from `meshseal render`)
        or, when it has none or `register` is set, find it by registration (assuming a vertical field
        of view `fov_y`), then read the mark under it; `quick` registers without the recut and the retry
        of more views (a scan where most pictures show other meshes: those read several times faster, and
        a few pictures of the right mesh are missed). Blind methods read the picture alone.

        Under `key` (None: the public key) each result says whether a mark is there at the false-
        positive rate `payload.FPR` (`detected`, `p_value`) and what it says (`message`); `expect`
        tests one known message instead (the p-value of the match). `pool` decides once for all the
        pictures (views of one asset), adding their evidence. Returns a Detection for one picture or
        for a pool, else a list.
        """
        original = self.original(mesh) if self.informed else None
        single = not isinstance(images, (list, tuple))
        readings = [self.look_again(self.read(image, original, register, fov_y, quick=quick), original, key, expect,
                                    search=not pool)
                    for image in ([images] if single else images)]
        if pool:
            return self.decision(readings, original, key, expect)
        results = [self.decision([reading], original, key, expect) for reading in readings]
        for image, reading, result in zip([images] if single else images, readings, results):
            if result.reason is None and result.detected is False and result.message is None:
                result.reason = self.previous_default_note(image, original, reading, key, expect)
        return results[0] if single else results

    def previous_default_note(self, image, original, reading: Reading, key=None, expect=None) -> str | None:
        """For the `default` model, where a picture reads no mark: the picture read again by each of
        PREVIOUS_DEFAULTS (the default's marks before) under the camera the reading used, and a note
        naming the first that detects its mark, its p-value times the number of models that may be
        tried (Bonferroni), so that the note holds at the same false-positive rate. None otherwise
        (another model, no camera, nothing read)."""
        from . import payload

        if self.name != "default" or original is None or reading.found is None:
            return None
        tried = 1 + len(PREVIOUS_DEFAULTS)
        for name, what in PREVIOUS_DEFAULTS.items():
            if name not in self._previous:
                self._previous[name] = load(name, str(self.device))
            previous = self._previous[name]
            try:
                again = previous.reader.read(image, original, camera=reading.found)
            except MeshsealError:
                continue
            found = previous.method.decide([again], key, expect)
            if found.p_value is None or not found.detected or not payload.detected(tried * found.p_value):
                continue
            said = f", message {found.message!r}" if found.message is not None else ""
            return (f"the picture carries a mark of the model `{name}` (p = {tried * found.p_value:.2g}{said}), "
                    f"{what}: read it with --model {name}")
        return None

    def original(self, mesh):
        """The original mesh (a Mesh, a path, or an already prepared one) ready for informed detection;
        prepare it once to detect many pictures of it."""
        return self.method.prepare(mesh)

    @torch.inference_mode()
    def read(self, image, original, register: bool = False, fov_y: float = 60.0, camera=None,
             quick: bool = False) -> Reading:
        """One picture's evidence, before any decision (`reading.read.Reader.read`)."""
        return self.reader.read(image, original, register, fov_y, camera, quick)

    @torch.inference_mode()
    def look_again(self, reading: Reading, original, key=None, expect=None, search: bool = True) -> Reading:
        """A registered reading looked at again where its mark is not found (`reading.second_look`)."""
        return look_again(self.reader, reading, original, key, expect, search)

    def decide(self, readings: list[Reading], key=None, expect=None) -> Detection:
        """The decision on readings' evidence (several: pooled), without the explanation (`decision`)."""
        return self.method.decide(readings, key, expect)

    def decision(self, readings: list[Reading], original, key=None, expect=None) -> Detection:
        """`decide`, with the reason a picture read no mark where a plausible mistake explains it."""
        result = self.method.decide(readings, key, expect)
        result.reason = self.why_not(result, original, key, readings[0] if len(readings) == 1 else None)
        return result

    def why_not(self, result: Detection, original, key=None, reading: Reading | None = None) -> str | None:
        """Why a picture read no mark, where a plausible mistake explains it, else None: the mesh
        given as the original is itself marked under `key` (`Method.own_mark_pvalue` under the FPR: a
        picture of it then reads nothing against it), or the picture's object does not match the
        original's silhouette under the picture's camera (IoU under SHOWS_MESH_BELOW: another mesh,
        or a registration gone astray). A mark made under another key is not told apart from no mark
        (docs/payload.md). A picture whose camera came from its metadata gets its silhouette IoU
        here (`result.silhouette_iou`), from its `reading`, only when it read no mark."""
        from . import payload

        if result.detected is not False or result.message is not None or original is None:
            return None  # (a message read, but not the one --expect names: no mistake to explain)
        if result.silhouette_iou is None and reading is not None and reading.object_mask is not None:
            from .reading.registration import silhouette_iou

            result.silhouette_iou = silhouette_iou(self.reader.on_cpu(original), reading.found.to("cpu"),
                                                   reading.object_mask)
        key_seed = self.method.key_seed(key)
        if self._own_of is None or self._own_of[0] is not original or self._own_of[1] != key_seed:
            self._own_of = (original, key_seed, self.method.own_mark_pvalue(original, key))
        own = self._own_of[2]
        if own is not None and payload.detected(own):
            return (f"the mesh given as the original is itself marked under this key (p = {own:.2g}): "
                    f"give the unmarked original with --mesh")
        if result.silhouette_iou is not None and result.silhouette_iou < SHOWS_MESH_BELOW:
            return f"the picture does not seem to show this mesh (silhouette IoU {result.silhouette_iou:.2f})"
        return None


def load(model: str | None = None, device: str | None = None) -> Watermarker:
    """Load a shipped model by name (default: 'default') or a checkpoint path (.safetensors)."""
    path = resolve_model(model)
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    return Watermarker(load_model(path, device), path.stem)



__all__ = ["load", "Watermarker", "Detection", "shipped_models", "parse_bits"]
