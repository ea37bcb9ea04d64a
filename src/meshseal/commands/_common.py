"""Argument types and helpers shared by the subcommands."""

from __future__ import annotations

import argparse
import math
import sys
import time


def vector3(text: str) -> tuple[float, float, float]:
    """'X,Y,Z' -> three finite floats (argparse type)."""
    parts = [p.strip() for p in text.replace(" ", ",").split(",") if p.strip()]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"expected three numbers X,Y,Z, got '{text}'")
    return values  # type: ignore[return-value]


def colour(text: str) -> tuple[float, float, float]:
    """'R,G,B' in [0, 1] (or 0-255 integers) -> three floats in [0, 1] (argparse type)."""
    try:
        values = vector3(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected a colour R,G,B in [0, 1], got '{text}'") from None
    if any(v > 1.0 for v in values) and all(float(v).is_integer() and 0 <= v <= 255 for v in values):
        values = tuple(v / 255.0 for v in values)
    if not all(0.0 <= v <= 1.0 for v in values):
        raise argparse.ArgumentTypeError(f"colour components must be in [0, 1] (or 0-255), got '{text}'")
    return values  # type: ignore[return-value]




def require_files(*checks) -> None:
    """(path, what) pairs: a one-line error for the first path that is not there, before any heavy import,
    so a mistyped name is answered at once. None paths are skipped; folders count as there."""
    from pathlib import Path

    from ..errors import MeshsealError

    for path, what in checks:
        if path is not None and not Path(path).exists():
            raise MeshsealError(f"{path}: no such {what}")


def require_mesh(path) -> None:
    """`require_files` for a mesh file (None: skipped), which must also be of a format meshseal reads (by
    its suffix)."""
    from ..mesh_formats import file_type

    require_files((path, "mesh file"))
    if path is not None:
        file_type(path)


def require_picture(path) -> None:
    """A picture file named on the command line that PIL does not recognise as an image (a text file, an
    empty one): its one-line error before torch is imported. Only the file's header is read; a picture
    that is recognised but damaged further on is answered by the reading, as before."""
    from pathlib import Path

    from ..errors import MeshsealError

    path = Path(path)
    if not path.is_file():
        return
    if path.stat().st_size == 0:
        raise MeshsealError(f"{path}: image file is empty")
    import warnings

    from PIL import Image, UnidentifiedImageError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # the reading judges the size
            with Image.open(path):
                pass
    except UnidentifiedImageError:
        raise MeshsealError(f"{path}: not a readable image (not an image format PIL reads)") from None
    except Exception:  # noqa: BLE001 - recognised but damaged, too large, unreadable: the reading says which
        pass


def require_messages(messages, model: str | None) -> None:
    """Messages (text or IDs) that cannot be messages of `model` (too long a text, too large an ID): their
    one-line error before torch is imported, the model's size read from its weights file's header. A
    model of a size without a payload schema is left to the command (it says so itself)."""
    from ..messages import SCHEMAS, payload_value
    from ..shipped import model_bits

    bits = model_bits(model)
    if bits in SCHEMAS:
        for message in messages:
            payload_value(message, bits)


def require_model(name: str | None) -> None:
    """A --model that names neither a shipped model nor a file: its one-line error before torch is imported."""
    from ..shipped import resolve_model

    resolve_model(name)


SAMPLERS = {"paper": "seed", "seed": "seed", "any": "any"}  # 'seed' (the seed paper's): the older name of 'paper'


def sampler(text: str) -> str:
    """--sampler: 'paper' (the camera and light ranges of the seed paper, Yoo et al. 2022) or 'any' (all
    around) -> the name `render.views.sample_views` takes; 'seed' is accepted for 'paper' (argparse type)."""
    if text not in SAMPLERS:
        raise argparse.ArgumentTypeError(f"expected 'paper' (the seed paper's camera range) or 'any', got '{text}'")
    return SAMPLERS[text]


def positive_int(limit: int, minimum: int = 1):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got '{text}'") from None
        if not minimum <= value <= limit:
            raise argparse.ArgumentTypeError(f"must be between {minimum} and {limit}, got {value}")
        return value
    return parse



class Stages:
    """Stage lines on stderr for a command that takes seconds ('meshseal: [  3.2 s] marking ...'), shown
    only on a terminal: never in stdout (--json stays one object), never in a pipe or a log."""

    def __init__(self, shown: bool | None = None):
        self.started = time.perf_counter()
        self.shown = sys.stderr.isatty() if shown is None else shown

    def __call__(self, text: str) -> None:
        if self.shown:
            print(f"meshseal: [{time.perf_counter() - self.started:5.1f} s] {text}", file=sys.stderr, flush=True)
