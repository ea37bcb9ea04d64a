"""Weights in safetensors (no pickle): the state dict plus the model config in the metadata."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from ..errors import MeshsealError
from .watermark import ModelConfig, WatermarkModel


def save_tensors(tensors: dict[str, torch.Tensor], path, metadata: dict[str, str]) -> None:
    """Atomic safetensors write, with the permissions the umask gives a new file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    from ..mesh.files import file_mode

    handle, temp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(handle)
    try:
        save_file({k: v.detach().contiguous().cpu() for k, v in tensors.items()}, temp, metadata=metadata)
        os.chmod(temp, file_mode())  # mkstemp's file is 0600: give the output the umask's permissions
        os.replace(temp, path)
    finally:
        if os.path.exists(temp):
            os.unlink(temp)


def save_model(model: WatermarkModel, path, extra: dict | None = None) -> None:
    metadata = {"format": "meshseal-model-1", "config": json.dumps(model.config.to_dict())}
    for key, value in (extra or {}).items():
        metadata[key] = value if isinstance(value, str) else json.dumps(value)
    save_tensors(model.state_dict(), path, metadata)


def read_metadata(path) -> dict:
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as handle:
        return dict(handle.metadata() or {})


def load_model(path, device="cpu") -> WatermarkModel:
    """Load a model saved by `save_model`; raises MeshsealError with one line on a bad file."""
    path = Path(path)
    if not path.is_file():
        raise MeshsealError(f"{path}: no such model file")
    try:
        metadata = read_metadata(path)
        if metadata.get("format") != "meshseal-model-1":
            raise MeshsealError(f"{path}: not a meshseal model (missing format metadata)")
        config = ModelConfig.from_dict(json.loads(metadata["config"]))
        model = WatermarkModel(config)
        model.load_state_dict(load_file(str(path), device="cpu"))
    except MeshsealError:
        raise
    except (SafetensorError, OSError, ValueError, KeyError, RuntimeError) as error:
        raise MeshsealError(f"{path}: cannot load model: {str(error).splitlines()[0][:200]}") from None
    return model.to(device).eval()
