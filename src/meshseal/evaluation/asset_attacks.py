"""What happens to a marked asset before anyone renders it: an engine's or a store's import pipeline.

Each attack is a function of a `Mesh` and a numpy Generator that returns a new `Mesh`: textures re-saved
as JPEG, halved, or block-compressed as GPUs sample them (BC1, BC7: encoded by etcpak, decoded by
texture2ddecoder), the file converted between OBJ and GLB by trimesh, or the mesh decimated keeping its
UVs. `ASSET_ATTACKS` names the suite `meshseal eval --attacks` runs on the marked mesh (the picture is
then rendered from the attacked asset and read against the original); `apply` runs one by name.
"""

from __future__ import annotations

import io
import tempfile
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from ..mesh import Mesh
from ..reading.imports import resized, to_bytes


def _each_texture(mesh: Mesh, change: Callable[[np.ndarray], np.ndarray]) -> Mesh:
    """`mesh` with every texture put through `change` (8-bit (H, W, 3) -> 8-bit (H', W', 3))."""
    def changed(texture: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(change(to_bytes(texture))).to(texture.device, texture.dtype) / 255.0

    return replace(mesh, materials=[m if m.texture is None else replace(m, texture=changed(m.texture))
                                    for m in mesh.materials])


def jpeg(texture: np.ndarray, quality: int) -> np.ndarray:
    """An 8-bit texture (H, W, 3) saved as JPEG at `quality` (Pillow's defaults: 4:2:0 chroma), read back."""
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(texture).save(buffer, format="JPEG", quality=quality)
    buffer.seek(0)
    with Image.open(buffer) as decoded:
        return np.asarray(decoded.convert("RGB")).copy()


def compress_blocks(texture: np.ndarray, kind: str) -> np.ndarray:
    """An 8-bit texture (H, W, 3) block-compressed as `kind` ('bc1' or 'bc7', etcpak's encoders) and
    decoded as a GPU samples it (texture2ddecoder); a size that is not a multiple of 4 is padded by its
    edge texels. Needs the `assets` extra."""
    try:
        import etcpak
        import texture2ddecoder
    except ImportError:
        from ..errors import MeshsealError

        raise MeshsealError("block compression needs etcpak and texture2ddecoder: "
                            "pip install 'meshseal[assets]'") from None
    height, width = texture.shape[:2]
    padded = np.pad(texture, ((0, -height % 4), (0, -width % 4), (0, 0)), mode="edge")
    rows, cols = padded.shape[:2]
    rgba = np.concatenate([padded, np.full((rows, cols, 1), 255, np.uint8)], axis=2)
    encode = etcpak.compress_bc1 if kind == "bc1" else etcpak.compress_bc7
    decode = texture2ddecoder.decode_bc1 if kind == "bc1" else texture2ddecoder.decode_bc7
    bgra = np.frombuffer(decode(encode(np.ascontiguousarray(rgba).tobytes(), cols, rows), cols, rows), np.uint8)
    return bgra.reshape(rows, cols, 4)[:height, :width, [2, 1, 0]].copy()


def texture_jpeg(quality: int) -> Callable:
    """Every texture saved as JPEG at `quality` (Pillow's defaults: 4:2:0 chroma) and read back."""
    return lambda mesh, rng: _each_texture(mesh, lambda texture: jpeg(texture, quality))


def texture_resize(factor: float) -> Callable:
    """Every texture resized by `factor` (Pillow's antialiased bicubic), as an engine's maximum texture
    size does on import; the UVs are unchanged, so the renderer samples the smaller image."""
    return lambda mesh, rng: _each_texture(mesh, lambda texture: resized(texture, factor))


def block_compressed(kind: str) -> Callable:
    """Every texture block-compressed as `kind` ('bc1' or 'bc7', etcpak's encoders) and decoded as a GPU
    samples it (texture2ddecoder); a size that is not a multiple of 4 is padded by its edge texels."""
    return lambda mesh, rng: _each_texture(mesh, lambda texture: compress_blocks(texture, kind))


def converted(mesh: Mesh, rng) -> Mesh:
    """Converted between OBJ and GLB by trimesh and read back: a mesh loaded from a file is saved in its
    own format and converted to the other (its images as trimesh re-encodes them); one made in memory
    goes both ways, GLB then OBJ, and keeps its frame."""
    import trimesh

    from ..mesh import load, save

    with tempfile.TemporaryDirectory(prefix="meshseal-convert-") as folder:
        folder = Path(folder)
        if mesh.source is not None:
            suffix = mesh.source.path.suffix.lower()
            other = ".obj" if suffix in (".glb", ".gltf") else ".glb"
            save(mesh, folder / f"asset{suffix}")
            trimesh.load(folder / f"asset{suffix}", force="scene").export(folder / f"converted{other}")
            return load(folder / f"converted{other}")
        save(replace(mesh, source=None), folder / "asset.glb")
        trimesh.load(folder / "asset.glb", force="scene").export(folder / "converted.obj")
        return replace(load(folder / "converted.obj"), up_axis=mesh.up_axis)


def decimated(keep: float) -> Callable:
    """Decimated to `keep` of its faces, keeping UVs (`mesh.simplify`: quadric error, each new vertex's
    UV interpolated where it lies on the original surface)."""
    def attack(mesh, rng):
        from ..mesh import simplify

        return simplify(replace(mesh, source=None), max(4, int(mesh.n_faces * keep)))
    return attack


ASSET_ATTACKS: dict[str, Callable] = {
    "texture_jpeg90": texture_jpeg(90),
    "texture_half": texture_resize(0.5),
    "texture_bc1": block_compressed("bc1"),
    "texture_bc7": block_compressed("bc7"),
    "obj_glb": converted,
    "decimate0.5": decimated(0.5),
}


def apply(name: str, mesh: Mesh, rng: np.random.Generator) -> Mesh:
    """Asset attack `name` on a Mesh -> a new Mesh (the input is not changed)."""
    return ASSET_ATTACKS[name](mesh, rng)
