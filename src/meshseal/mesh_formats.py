"""The mesh file formats meshseal reads, by suffix, without importing torch or trimesh (the command line
refuses another format at once)."""

from __future__ import annotations

from pathlib import Path

from .errors import MeshError

SUPPORTED = {".obj": "obj", ".glb": "glb", ".gltf": "gltf", ".ply": "ply", ".off": "off", ".stl": "stl"}


def file_type(path) -> str:
    """The format of a mesh file from its suffix ('obj', 'glb', ...); a one-line error for another one."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED:
        raise MeshError(f"{path}: unsupported mesh format '{suffix or path.name}' "
                        f"(supported: {', '.join(sorted(SUPPORTED))})")
    return SUPPORTED[suffix]
