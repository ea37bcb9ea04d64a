"""Readers that turn asset files into a plain numpy `RawMesh` for the data builder.

OBJ/GLB/glTF/PLY/STL go through `meshseal.mesh.load` (trimesh); OFF (including ModelNet's
"OFF<n> <m> 0" header quirk), AC3D (.ac, FlightGear) and 0 A.D.'s PMD are read here directly.
Every reader raises `MeshError` with a one-line message on bad input.
"""

from __future__ import annotations

import contextlib
import io
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

from ..errors import MeshError

MESH_SUFFIXES = {".obj", ".glb", ".gltf", ".ply", ".off", ".stl", ".ac", ".pmd"}
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tga", ".bmp", ".rgb", ".rgba", ".sgi", ".bw", ".dds", ".webp"}


@dataclass
class RawMaterial:
    name: str = "default"
    texture: np.ndarray | None = None  # (H, W, 3) uint8, row 0 = top
    diffuse: np.ndarray = field(default_factory=lambda: np.ones(3, dtype=np.float32))


@dataclass
class RawMesh:
    """An asset as the builder reads it: all parts concatenated, per-vertex positions/uvs, faces and a
    per-face material index.

    Not a `mesh.Mesh`, on purpose: the builder works in numpy float64 in its worker processes and derives
    normals only after welding and simplifying, so a RawMesh carries none; textures stay uint8 at file
    resolution (a Mesh holds float tensors, four times the bytes, and multi-material assets carry many
    large ones); a material needs only its texture and diffuse colour, to pack the atlas; and the OFF,
    AC3D and PMD readers build it without torch. The geometry applied to it (normals, spherical UVs,
    simplification, the Z-up rotation) is `meshseal.mesh`'s, see `data.process`.
    """

    positions: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) int64
    uvs: np.ndarray | None  # (V, 2) float64 or None
    face_material: np.ndarray  # (F,) int64
    materials: list[RawMaterial]
    up_axis: str = "y"

    def check(self, where: str) -> "RawMesh":
        if len(self.faces) == 0:
            raise MeshError(f"{where}: contains no triangle faces")
        if not np.isfinite(self.positions).all():
            raise MeshError(f"{where}: vertex positions contain NaN or infinity")
        if self.faces.min() < 0 or self.faces.max() >= len(self.positions):
            raise MeshError(f"{where}: face indices out of range")
        if self.uvs is not None and not np.isfinite(self.uvs).all():
            self.uvs = None
        return self


# ------------------------------------------------------------------ images


def _read_sgi(data: bytes) -> np.ndarray:
    """SGI .rgb/.rgba/.bw images (verbatim or RLE, 1 byte per channel), which Pillow rejects in some modes."""
    if len(data) < 512 or struct.unpack(">h", data[:2])[0] != 474:
        raise ValueError("not an SGI image")
    storage, bpc = data[2], data[3]
    _dim, xsize, ysize, zsize = struct.unpack(">HHHH", data[4:12])
    if bpc != 1:
        raise ValueError("16-bit SGI images are not supported")
    image = np.zeros((zsize, ysize, xsize), dtype=np.uint8)
    if storage == 0:
        image[:] = np.frombuffer(data, dtype=np.uint8, count=xsize * ysize * zsize, offset=512).reshape(
            zsize, ysize, xsize)
    else:
        n = ysize * zsize
        starts = np.frombuffer(data, dtype=">u4", count=n, offset=512)
        for index in range(n):
            z, y = divmod(index, ysize)
            pos, x, row = int(starts[index]), 0, image[z, y]
            while x < xsize and pos < len(data):
                control = data[pos]
                pos += 1
                count = control & 0x7F
                if count == 0:
                    break
                if control & 0x80:
                    row[x:x + count] = np.frombuffer(data, dtype=np.uint8, count=min(count, xsize - x), offset=pos)
                    pos += count
                else:
                    row[x:x + count] = data[pos]
                    pos += 1
                x += count
    image = image[:, ::-1]  # rows are stored bottom-up
    if zsize == 1:
        image = np.repeat(image, 3, axis=0)
    return np.ascontiguousarray(image[:3].transpose(1, 2, 0))


def read_image(source, name: str = "", alpha: str = "composite") -> np.ndarray:
    """Decode an image (path or bytes) to (H, W, 3) uint8, row 0 at the top.

    Decoding and its checks (regular files only, PIL's decompression-bomb limit, a one-line MeshError
    naming the image) are `mesh.validate.read_image`'s; this adds what the builder needs on top: SGI
    images in the modes Pillow rejects, and the alpha policy. alpha="composite" puts transparent pixels
    on white; "drop" ignores the alpha channel (game textures often keep masks, not transparency, there).
    A palette image with a transparent index is put on white under either policy.
    """
    from ..mesh import validate

    from_bytes = isinstance(source, (bytes, bytearray))
    name = name or ("" if from_bytes else str(source))
    data = bytes(source) if from_bytes else validate.read_regular(Path(source), "image file")
    try:
        image = validate.read_image(data, name)
    except MeshError:
        if data[:2] != b"\x01\xda":
            raise
        try:
            return _read_sgi(data)
        except Exception as sgi_error:
            raise MeshError(f"{name}: cannot read image: {sgi_error}") from None
    try:
        if (alpha == "composite" and image.mode in ("RGBA", "LA", "PA")) or (
                image.mode == "P" and "transparency" in image.info):
            image = Image.alpha_composite(Image.new("RGBA", image.size, (255, 255, 255, 255)), image.convert("RGBA"))
        return np.asarray(image.convert("RGB"), dtype=np.uint8).copy()
    except Exception as error:  # a mode PIL decodes but cannot convert
        raise MeshError(f"{name}: cannot read image: {str(error).splitlines()[0][:120]}") from None


# ------------------------------------------------------------------ trimesh formats (via meshseal.mesh)


def _from_meshseal(path: Path) -> RawMesh:
    from ..mesh import load

    with contextlib.redirect_stderr(io.StringIO()):  # missing-texture warnings: the builder counts them
        mesh = load(path)
    materials = []
    for material in mesh.materials:
        texture = None
        if material.texture is not None:
            texture = (material.texture.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)
        materials.append(RawMaterial(material.name, texture, material.diffuse.numpy().astype(np.float32)))
    return RawMesh(mesh.positions.double().numpy(), mesh.faces.numpy().astype(np.int64),
                   None if mesh.uvs is None else mesh.uvs.double().numpy(),
                   mesh.face_material.numpy().astype(np.int64), materials, mesh.up_axis)


# ------------------------------------------------------------------ OFF


def read_off(path: Path) -> RawMesh:
    lines = [line.split("#", 1)[0].strip() for line in Path(path).read_text(errors="replace").splitlines()]
    lines = [line for line in lines if line]
    if not lines or not lines[0].upper().startswith("OFF"):
        raise MeshError(f"{path}: not an OFF file (no OFF header)")
    head = lines[0][3:].split()  # ModelNet writes "OFF490 518 0" on one line
    body = lines[1:]
    try:
        if not head:
            head, body = body[0].split(), body[1:]
        n_verts, n_faces = int(head[0]), int(head[1])
        positions = np.asarray(" ".join(body[:n_verts]).split(), dtype=np.float64).reshape(n_verts, 3)
        faces = []
        for line in body[n_verts:n_verts + n_faces]:
            values = line.split()
            count = int(values[0])
            polygon = [int(v) for v in values[1:1 + count]]
            if len(polygon) != count:
                raise ValueError
            faces.extend([polygon[0], polygon[k], polygon[k + 1]] for k in range(1, count - 1))
    except (ValueError, IndexError):
        raise MeshError(f"{path}: truncated or malformed OFF data") from None
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    return RawMesh(positions, faces, None, np.zeros(len(faces), np.int64), [RawMaterial()], "z").check(str(path))


# ------------------------------------------------------------------ AC3D (FlightGear)


def _find_texture(name: str, base: Path, search_roots: list[Path]) -> Path | None:
    name = name.strip().strip('"')
    if not name:
        return None
    candidate = (base / name)
    if candidate.is_file():
        return candidate
    stem = Path(name).name
    for root in search_roots:
        for found in (root / stem,):
            if found.is_file():
                return found
    for root in search_roots:
        matches = list(root.rglob(stem)) if root.is_dir() else []
        if matches:
            return matches[0]
    return None


def read_ac(path: Path, search_roots: list[Path] | None = None, max_texture: int = 1024) -> RawMesh:
    """AC3D text files: a tree of OBJECTs with local rot/loc, polygon SURFs with per-corner uvs."""
    path = Path(path)
    lines = path.read_text(errors="replace").splitlines()
    if not lines or not lines[0].startswith("AC3D"):
        raise MeshError(f"{path}: not an AC3D file (no AC3D header)")
    colours: list[np.ndarray] = []
    positions, uvs, faces, face_keys = [], [], [], []
    keys: dict[tuple, int] = {}
    materials: list[RawMaterial] = []
    texture_cache: dict[str, np.ndarray | None] = {}
    n_vertices = 0
    cursor = 1

    def material_for(texture_name: str | None, mat: int) -> int:
        key = (texture_name, mat)
        if key not in keys:
            colour = colours[mat] if 0 <= mat < len(colours) else np.ones(3, np.float32)
            texture = None
            if texture_name:
                if texture_name not in texture_cache:
                    found = _find_texture(texture_name, path.parent, search_roots or [])
                    try:
                        texture_cache[texture_name] = None if found is None else _limit(read_image(found), max_texture)
                    except MeshError:
                        texture_cache[texture_name] = None
                texture = texture_cache[texture_name]
            keys[key] = len(materials)
            materials.append(RawMaterial(f"{texture_name}:{mat}", texture,
                                         np.ones(3, np.float32) if texture is not None else colour))
        return keys[key]

    def parse_object(rotation: np.ndarray, location: np.ndarray) -> None:
        nonlocal cursor, n_vertices
        local_rot, local_loc = np.eye(3), np.zeros(3)
        texture_name, texrep, texoff = None, np.ones(2), np.zeros(2)
        verts = np.zeros((0, 3))
        while cursor < len(lines):
            fields = lines[cursor].split()
            cursor += 1
            if not fields:
                continue
            tag = fields[0]
            if tag == "data":
                need = int(fields[1])
                got = 0
                while got < need and cursor < len(lines):
                    got += len(lines[cursor]) + 1
                    cursor += 1
            elif tag == "texture":
                texture_name = lines[cursor - 1].split(None, 1)[1].strip().strip('"')
            elif tag == "texrep":
                texrep = np.asarray(fields[1:3], dtype=np.float64)
            elif tag == "texoff":
                texoff = np.asarray(fields[1:3], dtype=np.float64)
            elif tag == "rot":
                local_rot = np.asarray(fields[1:10], dtype=np.float64).reshape(3, 3)
            elif tag == "loc":
                local_loc = np.asarray(fields[1:4], dtype=np.float64)
            elif tag == "numvert":
                count = int(fields[1])
                verts = np.asarray(" ".join(lines[cursor:cursor + count]).split(), dtype=np.float64).reshape(count, 3)
                cursor += count
            elif tag == "numsurf":
                world_rot = rotation @ local_rot
                world_loc = rotation @ local_loc + location
                world = verts @ world_rot.T + world_loc
                for _ in range(int(fields[1])):
                    flags, mat, refs = 0, 0, []
                    while cursor < len(lines):
                        sub = lines[cursor].split()
                        cursor += 1
                        if not sub:
                            continue
                        if sub[0] == "SURF":
                            flags = int(sub[1], 16)
                        elif sub[0] == "mat":
                            mat = int(sub[1])
                        elif sub[0] == "refs":
                            count = int(sub[1])
                            refs = [lines[cursor + k].split() for k in range(count)]
                            cursor += count
                            break
                    if flags & 0x0F != 0 or len(refs) < 3:
                        continue  # lines, not polygons
                    index = np.asarray([int(r[0]) for r in refs])
                    if index.max() >= len(verts):
                        raise MeshError(f"{path}: surface refers to a missing vertex")
                    corner_uv = np.asarray([[float(r[1]), float(r[2])] if len(r) >= 3 else [0.0, 0.0]
                                            for r in refs]) * texrep + texoff
                    material = material_for(texture_name, mat)
                    base = n_vertices
                    positions.append(world[index])
                    uvs.append(corner_uv)
                    n_vertices += len(index)
                    for k in range(1, len(index) - 1):
                        faces.append((base, base + k, base + k + 1))
                        face_keys.append(material)
            elif tag == "kids":
                for _ in range(int(fields[1])):
                    while cursor < len(lines) and not lines[cursor].startswith("OBJECT"):
                        cursor += 1
                    cursor += 1
                    parse_object(rotation @ local_rot, rotation @ local_loc + location)
                return

    try:
        for line in lines[1:]:
            if line.startswith("MATERIAL"):
                fields = line.split('"')[-1].split()
                rgb = fields.index("rgb") if "rgb" in fields else None
                colours.append(np.clip(np.asarray(fields[rgb + 1:rgb + 4], dtype=np.float32), 0, 1)
                               if rgb is not None else np.ones(3, np.float32))
        while cursor < len(lines) and not lines[cursor].startswith("OBJECT"):
            cursor += 1
        cursor += 1
        parse_object(np.eye(3), np.zeros(3))
    except MeshError:
        raise
    except (ValueError, IndexError) as error:
        raise MeshError(f"{path}: malformed AC3D data ({error})") from None
    if not faces:
        raise MeshError(f"{path}: contains no polygon surfaces")
    has_texture = any(m.texture is not None for m in materials)
    return RawMesh(np.concatenate(positions), np.asarray(faces, dtype=np.int64),
                   np.concatenate(uvs) if has_texture else None, np.asarray(face_keys, dtype=np.int64),
                   materials, "y").check(str(path))


# ------------------------------------------------------------------ PMD (0 A.D.)


def read_pmd(data: bytes, name: str, texture: np.ndarray | None = None) -> RawMesh:
    """0 A.D.'s binary mesh: PSMD header, vertices (pos, normal, uvs, blend), u16 triangles."""
    if data[:4] != b"PSMD":
        raise MeshError(f"{name}: not a PMD file")
    try:
        version, _size, n_verts = struct.unpack_from("<III", data, 4)
        offset = 16
        n_uv = 1
        if version >= 4:
            (n_uv,) = struct.unpack_from("<I", data, offset)
            offset += 4
        stride = 4 * (6 + 2 * n_uv) + 4 + 16
        vertex_dtype = np.dtype([("pos", "<f4", 3), ("normal", "<f4", 3), ("uv", "<f4", (n_uv, 2)),
                                 ("bones", "u1", 4), ("weights", "<f4", 4)])
        assert vertex_dtype.itemsize == stride
        vertices = np.frombuffer(data, dtype=vertex_dtype, count=n_verts, offset=offset)
        offset += stride * n_verts
        (n_faces,) = struct.unpack_from("<I", data, offset)
        faces = np.frombuffer(data, dtype="<u2", count=3 * n_faces, offset=offset + 4).reshape(-1, 3)
    except (struct.error, ValueError, AssertionError):
        raise MeshError(f"{name}: truncated PMD data") from None
    uv = vertices["uv"][:, 0].astype(np.float64) if n_uv > 0 else None
    if uv is not None:
        uv = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1)  # PMD stores v top-down (DirectX style)
    material = RawMaterial("pmd", texture)
    return RawMesh(vertices["pos"].astype(np.float64), faces.astype(np.int64),
                   uv if texture is not None else None, np.zeros(len(faces), np.int64), [material],
                   "y").check(name)


def _limit(image: np.ndarray, size: int) -> np.ndarray:
    if max(image.shape[:2]) <= size:
        return image
    pil = Image.fromarray(image)
    pil.thumbnail((size, size), Image.BILINEAR)
    return np.asarray(pil)


def read_mesh(path, search_roots: list[Path] | None = None, texture_path=None) -> RawMesh:
    """Read any supported mesh file into a RawMesh (MeshError on failure)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise MeshError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise MeshError(f"{path}: file is empty")
    if suffix == ".off":
        return read_off(path)
    if suffix == ".ac":
        return read_ac(path, search_roots)
    if suffix == ".pmd":
        texture = None
        if texture_path is not None and Path(texture_path).is_file():
            texture = _limit(read_image(texture_path, alpha="drop"), 1024)
        return read_pmd(path.read_bytes(), str(path), texture)
    if suffix in {".obj", ".glb", ".gltf", ".ply", ".stl"}:
        return _from_meshseal(path).check(str(path))
    raise MeshError(f"{path}: unsupported mesh format '{suffix}'")
