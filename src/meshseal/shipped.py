"""The models shipped inside the package, found by name without importing torch (the command line answers
a mistyped --model at once)."""

from __future__ import annotations

from pathlib import Path

from .errors import MeshsealError

WEIGHTS_DIR = Path(__file__).parent / "weights"
DEFAULT_MODEL = "default"


def shipped_names() -> list[str]:
    """The shipped models' names, sorted (their weights' file names)."""
    return sorted(path.stem for path in WEIGHTS_DIR.glob("*.safetensors"))


def resolve_model(name_or_path: str | None) -> Path:
    """The weights file of a shipped model's name or of a path (None: the default model); a one-line
    error for anything else."""
    if name_or_path is None:
        name_or_path = DEFAULT_MODEL
    path = Path(name_or_path)
    if path.suffix == ".safetensors" or path.exists():
        return path
    shipped = WEIGHTS_DIR / f"{name_or_path}.safetensors"
    if shipped.is_file():
        return shipped
    names = ", ".join(shipped_names()) or "none"
    raise MeshsealError(f"unknown model '{name_or_path}' (shipped: {names}; or give a .safetensors path)")


def model_bits(name_or_path: str | None) -> int | None:
    """How many raw bits a model carries, from its weights file's header (safetensors: an 8-byte length,
    then JSON whose metadata holds the model's config), without torch; None where the file does not say
    (the model's loading then answers)."""
    import json
    import struct

    try:
        with resolve_model(name_or_path).open("rb") as file:
            (length,) = struct.unpack("<Q", file.read(8))
            if length > 1 << 24:  # not a header this size: not a weights file meshseal wrote
                return None
            metadata = json.loads(file.read(length)).get("__metadata__") or {}
        bits = json.loads(metadata.get("config", "{}")).get("n_bits")
    except (OSError, ValueError, struct.error, AttributeError):
        return None
    return bits if isinstance(bits, int) and not isinstance(bits, bool) else None
