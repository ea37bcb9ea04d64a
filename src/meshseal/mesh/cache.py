"""A cache of loaded meshes, so that a command reading pictures of a mesh it has met before skips trimesh.

Loading a mesh through trimesh costs its import (with scipy's and networkx's) before any file is read; a
command that only reads the mesh (`meshseal detect`, `meshseal render`) needs the arrays alone.
`io.load(path, cache=True)` keeps them here after a first load and takes them from here after that, for
the same input: the key is the SHA-256 of the mesh file and of every file its load reads (an OBJ's MTL
and textures), the up axis asked for, the loader's own source files and the versions of trimesh, numpy
and Pillow, so a changed texture, loader or library is a new entry. The file's own checks (`validate`)
run either way, with their errors and warnings. A mesh from the cache has no trimesh scene: it cannot be
saved (`io.save` says so); `meshseal embed`, which saves, loads with trimesh and fills the cache for the
commands after it (`io.load(path, cache="fill")`).

Entries are safetensors files (no pickle): the mesh's tensors, its textures as 8-bit where they came from
8-bit images (the same floats back), and a JSON header for the rest. Where: `MESHSEAL_CACHE` (a folder,
or `off`), else `$XDG_CACHE_HOME/meshseal/meshes`, else `~/.cache/meshseal/meshes`; entries are written
atomically with the user's umask, and the least recently used go once the folder holds over
`LIMIT_BYTES`. A cache that cannot be read or written is passed over silently: it only ever saves time.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import torch

FORMAT = 1  # this file's layout of an entry; part of every key
LIMIT_BYTES = 1 << 30  # the folder's size past which the least recently used entries go
_LOADER = ("io.py", "validate.py", "preprocess.py", "core.py", "cache.py")  # the code a loaded mesh depends on


def folder() -> Path | None:
    """The cache's folder, or None where `MESHSEAL_CACHE` turns it off (`off`, `0`, `no`, empty)."""
    setting = os.environ.get("MESHSEAL_CACHE")
    if setting is not None:
        return None if setting.strip().lower() in {"", "0", "off", "no", "false"} else Path(setting).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "meshseal" / "meshes"


def _trimesh_version() -> str:
    """trimesh's installed version from its dist-info folder's name, without importing it (or the
    stat of its package where that is not found)."""
    import importlib.util

    spec = importlib.util.find_spec("trimesh")
    if spec is None or spec.origin is None:
        return "none"
    package = Path(spec.origin).parent
    try:
        names = [n for n in os.listdir(package.parent) if n.startswith("trimesh-") and n.endswith(".dist-info")]
    except OSError:
        names = []
    if len(names) == 1:
        return names[0]
    status = os.stat(spec.origin)
    return f"{spec.origin}:{status.st_size}:{status.st_mtime_ns}"


_CODE_DIGEST: list[str] = []


def _code_digest() -> str:
    """The loader's source files and the libraries it loads with, as one digest (computed once)."""
    if not _CODE_DIGEST:
        from PIL import __version__ as pillow

        digest = hashlib.sha256(f"{FORMAT}|{_trimesh_version()}|{np.__version__}|{pillow}".encode())
        here = Path(__file__).parent
        for name in _LOADER:
            digest.update((here / name).read_bytes())
        _CODE_DIGEST.append(digest.hexdigest())
    return _CODE_DIGEST[0]


def key(path: Path, data: bytes, file_type: str, up_axis: str, inputs) -> str | None:
    """The entry's name for a load of `path` (its bytes `data`) reading the other files `inputs`,
    or None where the cache is off or an input cannot be read."""
    if folder() is None:
        return None
    digest = hashlib.sha256(f"{_code_digest()}|{file_type}|{up_axis}".encode())
    digest.update(hashlib.sha256(data).digest())
    mesh_file = Path(path).resolve()
    base = mesh_file.parent
    others = sorted({Path(p).resolve() for p in inputs} - {mesh_file})
    for other in others:
        try:
            name = os.path.relpath(other, base)
            digest.update(name.encode() + b"\0" + hashlib.sha256(other.read_bytes()).digest())
        except (OSError, ValueError):
            return None
    return digest.hexdigest()


def _entry(name: str) -> Path:
    return folder() / f"{name}.safetensors"


def read(name: str | None) -> tuple[dict, dict] | None:
    """The entry `name`: (its JSON header, its tensors), or None (no entry, or one that cannot be read)."""
    if name is None:
        return None
    entry = _entry(name)
    try:
        from safetensors import safe_open

        with safe_open(str(entry), framework="pt") as stored:
            header = json.loads(stored.metadata()["meshseal"])
            tensors = {k: stored.get_tensor(k) for k in stored.keys()}
    except Exception:  # noqa: BLE001 - missing, unreadable, foreign or damaged: a miss
        return None
    try:
        os.utime(entry)  # recently used
    except OSError:
        pass
    return header, tensors


def write(name: str | None, header: dict, tensors: dict) -> None:
    """Keep an entry (a JSON header, tensors) under `name`; silently nothing where that fails."""
    if name is None:
        return
    try:
        from safetensors.torch import save

        from .files import atomic_write

        data = save({k: v.detach().cpu().contiguous() for k, v in tensors.items()},
                    metadata={"meshseal": json.dumps(header)})
        atomic_write(_entry(name), data)
        _prune()
    except Exception:  # noqa: BLE001 - a cache that cannot be written only costs time
        return


def eight_bit(texture: torch.Tensor) -> torch.Tensor:
    """A texture (float, from an 8-bit image as `io` reads one) as 8-bit where that gives back the same
    floats (`from_eight_bit`), else as it is."""
    eight = torch.round(texture * 255.0).to(torch.uint8)
    return eight if torch.equal(from_eight_bit(eight), texture) else texture


def from_eight_bit(texture: torch.Tensor) -> torch.Tensor:
    """`eight_bit`'s inverse: an 8-bit texture as the floats `io` makes of an image (others as they are)."""
    if texture.dtype != torch.uint8:
        return texture
    return torch.from_numpy(texture.numpy().astype(np.float32) / 255.0)


def _prune() -> None:
    """The least recently used entries removed while the folder holds over LIMIT_BYTES."""
    entries = []
    for entry in folder().glob("*.safetensors"):
        try:
            status = entry.stat()
        except OSError:
            continue
        entries.append((status.st_mtime_ns, status.st_size, entry))
    total = sum(size for _, size, _ in entries)
    for _, size, entry in sorted(entries, key=lambda e: e[0]):
        if total <= LIMIT_BYTES:
            break
        try:
            entry.unlink()
        except OSError:
            continue
        total -= size


def glb_external(data: bytes) -> bool:
    """Whether a GLB (already checked) names files outside itself (a buffer or an image by a URI that is
    not a data: URI): such a load reads files the key would not see, so it is not cached."""
    import struct

    size = struct.unpack_from("<I", data, 12)[0]
    document = json.loads(data[20:20 + size])
    if not isinstance(document, dict):  # nothing the key can vouch for
        return True
    return any(isinstance(item, dict) and isinstance(item.get("uri"), str) and not item["uri"].startswith("data:")
               for kind in ("buffers", "images") for item in (document.get(kind) or []))
