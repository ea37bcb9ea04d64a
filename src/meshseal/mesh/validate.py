"""Strict checks around the libraries that read files: only regular files, and structures that add up.

trimesh is forgiving: it reads what it can and silently drops or wraps what it cannot (a face cut off
at the end of the file, an OBJ index 0, a header count larger than the data, a glTF accessor reaching
past its buffer). A watermark embedded into such a silently mangled mesh is data loss found later, so
each check here refuses a file whose structure does not add up, with one line naming the file and the
problem. trimesh still does the parsing; these checks only count and bound what it will read.
"""

from __future__ import annotations

import base64
import binascii
import io
import json
import math
import os
import re
import stat
import struct
import warnings
from pathlib import Path

import numpy as np

from ..errors import MeshError

# ---------------------------------------------------------------- files


def regular_file(path: Path, what: str = "file") -> os.stat_result:
    """stat() a file that is about to be read; anything but an existing regular file is a MeshError.

    A named pipe or a device would block or never end, so those are refused before anything opens them.
    """
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise MeshError(f"{path}: no such {what}") from None
    except OSError as error:
        raise MeshError(f"{path}: cannot read {what}: {error.strerror or error}") from None
    if stat.S_ISDIR(info.st_mode):
        raise MeshError(f"{path}: is a directory, not a {what}")
    if not stat.S_ISREG(info.st_mode):
        kind = ("a named pipe" if stat.S_ISFIFO(info.st_mode) else "a device" if stat.S_ISCHR(info.st_mode)
                or stat.S_ISBLK(info.st_mode) else "a socket" if stat.S_ISSOCK(info.st_mode) else "a special file")
        raise MeshError(f"{path}: is {kind}, not a regular {what}; only regular files are read")
    return info


def resolved(path: Path, what: str = "file") -> Path:
    """`Path.resolve()`, with a symbolic link loop (a RuntimeError or OSError from pathlib) raised as a
    one-line MeshError naming the path."""
    try:
        return Path(path).resolve()
    except (RuntimeError, OSError) as error:
        detail = "is a symbolic link loop" if "loop" in str(error).lower() or getattr(error, "errno", None) == 40 \
            else f"cannot be resolved ({getattr(error, 'strerror', None) or error})"
        raise MeshError(f"{path}: {detail}; cannot read {what}") from None


def read_regular(path: Path, what: str = "file") -> bytes:
    """The bytes of a regular file (see `regular_file`)."""
    regular_file(path, what)
    try:
        return Path(path).read_bytes()
    except OSError as error:
        raise MeshError(f"{path}: cannot read {what}: {error.strerror or error}") from None


def find_asset(folder: Path, name: str) -> Path | None:
    """The file trimesh's resolver opens for an asset `name` (an MTL, a texture, a glTF buffer or image)
    referenced from a file in `folder`: the name, then without a leading '/', then its base name, inside
    `folder` only (trimesh refuses paths that lead out of it). None when there is none."""
    root = resolved(folder, "folder")
    for candidate in (name.strip(), name.strip().lstrip("/"), os.path.split(name)[-1]):
        path = resolved(root / candidate.strip(), f"file '{name.strip()}'")
        if path.is_relative_to(root) and path.exists():
            return path
    return None


JPEG_CODEC_KEY = "meshseal:jpeg_codec"  # read_image's note of a JPEG file's own codec (see _jpeg_codec)


def _jpeg_codec(opened) -> tuple | None:
    """A JPEG file's own encoder settings, as `reading.compression` re-encodes with them: ("JPEG",
    quantization tables, chroma subsampling), for a 3-component YCbCr baseline picture stored upright
    (an EXIF rotation moves its 8x8 blocks); None for anything else (grey, CMYK, rotated)."""
    from PIL import JpegImagePlugin

    try:
        sampling = JpegImagePlugin.get_sampling(opened)
        tables = {int(k): list(v) for k, v in dict(opened.quantization).items()}
        rotated = opened.getexif().get(0x0112, 1) not in (1, None)
    except Exception:
        return None
    if opened.mode != "RGB" or sampling not in (0, 1, 2) or len(tables) not in (2, 3) or rotated:
        return None
    return ("JPEG", tables, sampling)


def read_image(source, name, min_side: int = 1):
    """Decode an image (a path or bytes) with PIL, fully, under PIL's decompression-bomb limit.

    Returns the loaded PIL image (first frame of an animation). `name` names it in the MeshError raised
    for anything unreadable: not an image, truncated, over the pixel limit, smaller than `min_side`.
    """
    from PIL import Image

    if isinstance(source, (str, Path)):
        source = read_regular(Path(source), "image file")
    if not source:
        raise MeshError(f"{name}: image file is empty")
    limit = Image.MAX_IMAGE_PIXELS
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(source)) as opened:
                opened.load()
                image = opened.copy()
                image.info = dict(opened.info)
                image.format = opened.format  # (a copy has none) the file's format, for the codec step
                if opened.format == "JPEG":  # its own tables: what the codec step of informed reading tries
                    image.info[JPEG_CODEC_KEY] = _jpeg_codec(opened)
    except (Image.DecompressionBombError, Image.DecompressionBombWarning):
        raise MeshError(f"{name}: image claims more than {limit} pixels (a decompression bomb?); "
                        f"refusing to decode it") from None
    except MemoryError:
        raise MeshError(f"{name}: image too large to decode") from None
    except Exception as error:  # PIL raises OSError, SyntaxError, ValueError, struct.error, ... on corrupt data
        detail = str(error).strip().splitlines()[0][:120] if str(error).strip() else type(error).__name__
        if "cannot identify image file" in detail:
            detail = "not an image format PIL reads"
        raise MeshError(f"{name}: not a readable image ({detail})") from None
    width, height = image.size
    if min(width, height) < min_side:
        raise MeshError(f"{name}: picture is {width}x{height} pixels, too small (at least {min_side} "
                        f"pixels a side)")
    return image


# ---------------------------------------------------------------- OBJ

_OBJ_VALUES = {"v": (3, 7), "vt": (1, 3), "vn": (3, 3)}


def _numbers(values: list[str]) -> bool:
    try:
        for value in values:
            float(value)
    except ValueError:
        return False
    return True


def check_obj(path: Path, data: bytes) -> None:
    """Vertex records hold numbers; every face has 3+ corners whose v/vt/vn indices name existing
    records (1-based; negative counts back from the records read so far)."""
    counts = {"v": 0, "vt": 0, "vn": 0}
    highest = {"v": (0, 0), "vt": (0, 0), "vn": (0, 0)}  # kind -> (largest positive index, its line)
    kinds = ("v", "vt", "vn")
    for number, line in enumerate(data.decode("utf-8", "replace").splitlines(), 1):
        fields = line.split()
        if not fields:
            continue
        key = fields[0]
        if key in _OBJ_VALUES:
            low, high = _OBJ_VALUES[key]
            if not low <= len(fields) - 1 <= high or not _numbers(fields[1:]):
                raise MeshError(f"{path}: line {number}: a '{key}' record needs {low}"
                                f"{'' if low == high else f' to {high}'} numbers, got '{line.strip()[:60]}'")
            counts[key] += 1
        elif key == "f":
            if len(fields) < 4:
                raise MeshError(f"{path}: line {number}: a face needs at least 3 corners, got '{line.strip()[:60]}'")
            for corner in fields[1:]:
                parts = corner.split("/")
                if len(parts) > 3 or not parts[0]:
                    raise MeshError(f"{path}: line {number}: malformed face corner '{corner[:30]}'")
                for kind, text in zip(kinds, parts):
                    if not text:
                        continue
                    try:
                        index = int(text)
                    except ValueError:
                        raise MeshError(f"{path}: line {number}: face corner '{corner[:30]}' is not "
                                        f"a whole number") from None
                    if index == 0:
                        raise MeshError(f"{path}: line {number}: face uses {kind} index 0 "
                                        f"(OBJ indices start at 1)")
                    if index < 0 and -index > counts[kind]:
                        raise MeshError(f"{path}: line {number}: face uses {kind} index {index}, but only "
                                        f"{counts[kind]} {kind} records come before it")
                    if index > highest[kind][0]:
                        highest[kind] = (index, number)
    for kind in kinds:
        index, number = highest[kind]
        if index > counts[kind]:
            raise MeshError(f"{path}: line {number}: face uses {kind} index {index}, but the file has only "
                            f"{counts[kind]} {kind} records")


# ---------------------------------------------------------------- PLY

PLY_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
PLY_TYPES = {"char", "uchar", "short", "ushort", "int", "uint", "float", "double", "int8", "uint8", "int16",
             "uint16", "int32", "uint32", "float32", "float64"}


def _ply_header(path: Path, data: bytes) -> tuple[str, list[tuple[str, int, list[bool]]], int, int]:
    """(format, [(element name, count, [property is a list])], header lines, offset of the body)."""
    match = re.search(rb"end_header[ \t]*\r?\n", data[:1 << 20])
    if not data.startswith(b"ply") or match is None:
        raise MeshError(f"{path}: not a PLY file (no 'ply' ... 'end_header' header)")
    lines = data[:match.start()].decode("ascii", "replace").splitlines()
    if lines[0].strip() != "ply":
        raise MeshError(f"{path}: not a PLY file (first line is not 'ply')")
    fmt, elements = None, []
    for number, line in enumerate(lines[1:], 2):
        fields = line.split()
        if not fields or fields[0] in ("comment", "obj_info"):
            continue
        if fields[0] == "format":
            if len(fields) != 3 or fields[1] not in PLY_FORMATS or fields[2] != "1.0":
                raise MeshError(f"{path}: line {number}: '{line.strip()[:60]}' names no PLY format "
                                f"(format ascii|binary_little_endian|binary_big_endian 1.0)")
            fmt = fields[1]
        elif fields[0] == "element":
            if len(fields) != 3 or not fields[2].isdigit():
                raise MeshError(f"{path}: line {number}: malformed element line '{line.strip()[:60]}' "
                                f"(element NAME COUNT, COUNT >= 0)")
            elements.append((fields[1], int(fields[2]), []))
        elif fields[0] == "property":
            is_list = len(fields) == 5 and fields[1] == "list"
            types = fields[2:4] if is_list else fields[1:2]
            if not elements or len(fields) != (5 if is_list else 3) or not set(types) <= PLY_TYPES:
                raise MeshError(f"{path}: line {number}: malformed property line '{line.strip()[:60]}'")
            elements[-1][2].append(is_list)
        else:
            raise MeshError(f"{path}: line {number}: unknown PLY header line '{line.strip()[:60]}'")
    if fmt is None:
        raise MeshError(f"{path}: PLY header has no format line")
    return fmt, elements, len(lines) + 1, match.end()


def check_ply(path: Path, data: bytes) -> None:
    """A header naming a real format, known types and element counts; an ASCII body holding exactly the
    records the header promises, each with the values its properties need. (trimesh already requires a
    binary body to have exactly the promised length.)"""
    fmt, elements, header_lines, start = _ply_header(path, data)
    if fmt != "ascii":
        return
    lines = [(number, line.split()) for number, line in
             enumerate(data[start:].decode("ascii", "replace").splitlines(), header_lines + 1) if line.strip()]
    position = 0
    for name, count, properties in elements:
        rows = lines[position:position + count]
        if len(rows) < count:
            raise MeshError(f"{path}: cut off: the header promises {count} '{name}' records, the file holds "
                            f"{len(rows)}")
        for number, values in rows:
            needed, index = 0, 0
            for is_list in properties:
                if is_list:
                    try:
                        length = int(values[index]) if index < len(values) else -1
                    except ValueError:
                        length = -1
                    if length < 0:
                        needed = -1
                        break
                    needed += 1 + length
                    index += 1 + length
                else:
                    needed += 1
                    index += 1
            if needed != len(values):
                raise MeshError(f"{path}: line {number}: a '{name}' record has {len(values)} values, its "
                                f"properties need {needed if needed >= 0 else 'a list length first'}")
        position += count
    if position < len(lines):
        raise MeshError(f"{path}: line {lines[position][0]}: {len(lines) - position} more lines than the "
                        f"header's element counts promise")


# ---------------------------------------------------------------- OFF


def check_off(path: Path, data: bytes) -> None:
    """An OFF keyword, vertex and face counts, then exactly that many vertex lines (3+ numbers) and face
    lines ('n i1 .. in', n >= 3, indices naming vertices); nothing else but comments."""
    text = re.sub(r"#[^\n]*", "", data.decode("utf-8", "replace"))
    lines = [(number, line.split()) for number, line in enumerate(text.splitlines(), 1) if line.strip()]
    if not lines or not re.fullmatch(r"(ST)?C?N?OFF", lines[0][1][0]):
        raise MeshError(f"{path}: not an OFF file (first word is not OFF)")
    counts = lines[0][1][1:] or (lines[1][1] if len(lines) > 1 else [])
    body = lines[1:] if lines[0][1][1:] else lines[2:]
    if len(counts) < 2 or not all(c.isdigit() for c in counts[:3]):
        raise MeshError(f"{path}: malformed OFF count line '{' '.join(counts)[:60]}' (vertices faces edges)")
    n_vertices, n_faces = int(counts[0]), int(counts[1])
    if len(body) < n_vertices + n_faces:
        held_v = min(len(body), n_vertices)
        raise MeshError(f"{path}: cut off: the header promises {n_vertices} vertices and {n_faces} faces, the "
                        f"file holds {held_v} and {len(body) - held_v}")
    if len(body) > n_vertices + n_faces:
        raise MeshError(f"{path}: line {body[n_vertices + n_faces][0]}: {len(body) - n_vertices - n_faces} more "
                        f"lines than the header's {n_vertices} vertices and {n_faces} faces")
    for number, values in body[:n_vertices]:
        if len(values) < 3 or not _numbers(values[:3]):
            raise MeshError(f"{path}: line {number}: a vertex needs 3 numbers, got '{' '.join(values)[:60]}'")
    for number, values in body[n_vertices:]:
        try:
            corners = int(values[0])
            indices = [int(v) for v in values[1:1 + corners]]
        except ValueError:
            raise MeshError(f"{path}: line {number}: malformed face '{' '.join(values)[:60]}'") from None
        if corners < 3 or len(indices) != corners:
            raise MeshError(f"{path}: line {number}: a face needs a corner count of 3 or more and that many "
                            f"indices, got '{' '.join(values)[:60]}'")
        if min(indices) < 0 or max(indices) >= n_vertices:
            raise MeshError(f"{path}: line {number}: face index out of range (0 to {n_vertices - 1})")


# ---------------------------------------------------------------- STL

_STL_NEXT = {"solid": {"facet", "endsolid"}, "facet": {"outer"}, "outer": {"vertex"}, "vertex": {"vertex", "endloop"},
             "endloop": {"endfacet"}, "endfacet": {"facet", "endsolid"}, "endsolid": {"solid"}}


def check_stl(path: Path, data: bytes) -> None:
    """A binary STL has exactly 84 + 50 x (its triangle count) bytes; an ASCII one is a sequence of
    complete solid / facet / outer loop / 3 vertices / endloop / endfacet / endsolid blocks."""
    if len(data) >= 84 and len(data) == 84 + 50 * struct.unpack_from("<I", data, 80)[0]:
        return
    ascii_like = data.lstrip()[:5].lower() == b"solid" and b"\x00" not in data[:1 << 16]
    if not ascii_like:
        promised = struct.unpack_from("<I", data, 80)[0] if len(data) >= 84 else None
        detail = (f"its header promises {promised} triangles ({84 + 50 * promised} bytes), the file has "
                  f"{len(data)} bytes" if promised is not None else "shorter than the 84-byte header")
        raise MeshError(f"{path}: not a valid binary STL: {detail}")
    state, corners = "endsolid", 0
    for number, line in enumerate(data.decode("utf-8", "replace").splitlines(), 1):
        fields = line.split()
        if not fields:
            continue
        word = fields[0].lower()
        if word not in _STL_NEXT[state] or (word == "vertex" and (len(fields) != 4 or not _numbers(fields[1:]))):
            raise MeshError(f"{path}: line {number}: unexpected '{line.strip()[:60]}' in an ASCII STL "
                            f"(after '{state}')")
        corners = corners + 1 if word == "vertex" else 0 if word == "outer" else corners
        if word == "endloop" and corners != 3:
            raise MeshError(f"{path}: line {number}: a facet has {corners} vertices, not 3")
        state = word
    if state != "endsolid":
        raise MeshError(f"{path}: cut off: the ASCII STL ends inside a solid (no 'endsolid')")


# ---------------------------------------------------------------- glTF / GLB

_COMPONENT_BYTES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
_COMPONENT_DTYPE = {5120: "i1", 5121: "u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_TYPE_SIZE = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_UNREADABLE_EXTENSIONS = {"KHR_draco_mesh_compression", "EXT_meshopt_compression", "KHR_meshopt_compression"}


class _Gltf:
    """Checks one glTF document against its binary buffers."""

    def __init__(self, path: Path, document, buffers: list[bytes | None]):
        self.path, self.doc, self.buffers = path, document, buffers

    def fail(self, message: str):
        raise MeshError(f"{self.path}: {message}")

    def items(self, key: str) -> list:
        value = self.doc.get(key, [])
        if not isinstance(value, list) or not all(isinstance(item, dict) for item in value):
            self.fail(f"'{key}' is not a list of objects")
        return value

    def integer(self, value, what: str, low: int = 0, high: int | None = None) -> int:
        """`value` as a whole number in [low, high) (high None: no upper bound)."""
        if isinstance(value, bool) or not isinstance(value, int) or value < low or (high is not None and value >= high):
            if high is not None and high <= low:
                self.fail(f"{what} refers to an entry of an empty list")
            bound = f"from {low} to {high - 1}" if high is not None else f">= {low}"
            self.fail(f"{what} is {json.dumps(value)[:40]}, expected a whole number {bound}")
        return value

    def index(self, value, what: str, key: str) -> int:
        return self.integer(value, what, 0, len(self.items(key)))

    def check(self) -> None:
        doc = self.doc
        if not isinstance(doc, dict):
            self.fail("the glTF JSON is not an object")
        version = str((doc.get("asset") or {}).get("version", "")) if isinstance(doc.get("asset"), dict) else ""
        if not version.startswith("2."):
            self.fail(f"glTF asset version is '{version[:20]}'; only glTF 2.x is read")
        required = set(doc.get("extensionsRequired") or []) & _UNREADABLE_EXTENSIONS
        if required:
            self.fail(f"needs the {', '.join(sorted(required))} extension, which meshseal cannot read")
        sizes = []
        for number, buffer in enumerate(self.items("buffers")):
            length = self.integer(buffer.get("byteLength"), f"buffer {number} byteLength", 1)
            held = self.buffers[number] if number < len(self.buffers) else None
            if held is None or len(held) < length:
                self.fail(f"buffer {number} promises {length} bytes, the data holds "
                          f"{0 if held is None else len(held)} (cut off?)")
            sizes.append(length)
        views = self.items("bufferViews")
        for number, view in enumerate(views):
            what = f"bufferView {number}"
            buffer = self.index(view.get("buffer"), f"{what} buffer", "buffers")
            offset = self.integer(view.get("byteOffset", 0), f"{what} byteOffset")
            length = self.integer(view.get("byteLength"), f"{what} byteLength", 1)
            if "byteStride" in view:
                stride = self.integer(view["byteStride"], f"{what} byteStride", 4, 253)
                if stride % 4:
                    self.fail(f"{what} byteStride {stride} is not a multiple of 4")
            if offset + length > sizes[buffer]:
                self.fail(f"{what} reaches byte {offset + length} of buffer {buffer}, which has {sizes[buffer]}")
        accessors = self.items("accessors")
        for number in range(len(accessors)):
            self.accessor(number)
        for number, mesh in enumerate(self.items("meshes")):
            primitives = mesh.get("primitives")
            if not isinstance(primitives, list) or not primitives:
                self.fail(f"mesh {number} has no primitives")
            for k, primitive in enumerate(primitives):
                self.primitive(primitive, f"mesh {number} primitive {k}")
        nodes = self.items("nodes")
        parents: dict[int, int] = {}
        for number, node in enumerate(nodes):
            if "mesh" in node:
                self.index(node["mesh"], f"node {number} mesh", "meshes")
            children = node.get("children", [])
            if not isinstance(children, list):
                self.fail(f"node {number} children is not a list")
            for child in children:
                child = self.index(child, f"node {number} child", "nodes")
                if child in parents or child == number:
                    self.fail(f"node {child} has more than one parent (the node graph must be a tree)")
                parents[child] = number
            matrix = node.get("matrix")
            if matrix is not None and (not isinstance(matrix, list) or len(matrix) != 16 or not all(
                    isinstance(v, (int, float)) and math.isfinite(v) for v in matrix)):
                self.fail(f"node {number} matrix is not 16 finite numbers")
        for number in parents:  # a node graph with a cycle would send a reader round forever
            seen, current = set(), number
            while current in parents:
                if current in seen:
                    self.fail(f"node {number}: the node graph has a cycle")
                seen.add(current)
                current = parents[current]
        for number, scene in enumerate(self.items("scenes")):
            if not isinstance(scene.get("nodes", []), list):
                self.fail(f"scene {number} nodes is not a list")
            for node in scene.get("nodes", []):
                self.index(node, f"scene {number} node", "nodes")
        for number, texture in enumerate(self.items("textures")):
            if "source" in texture:
                self.index(texture["source"], f"texture {number} source", "images")
        for number, material in enumerate(self.items("materials")):
            base = (material.get("pbrMetallicRoughness") or {}).get("baseColorTexture")
            if isinstance(base, dict):
                self.index(base.get("index"), f"material {number} baseColorTexture", "textures")

    def view_bytes(self, number: int) -> bytes:
        view = self.items("bufferViews")[number]
        data = self.buffers[view["buffer"]]
        offset = view.get("byteOffset", 0)
        return data[offset:offset + view["byteLength"]]

    def accessor(self, number: int) -> None:
        accessor = self.items("accessors")[number]
        what = f"accessor {number}"
        count = self.integer(accessor.get("count"), f"{what} count", 1)
        component = accessor.get("componentType")
        if component not in _COMPONENT_BYTES:
            self.fail(f"{what} componentType {json.dumps(component)[:20]} is not a glTF component type")
        if accessor.get("type") not in _TYPE_SIZE:
            self.fail(f"{what} type {json.dumps(accessor.get('type'))[:20]} is not a glTF accessor type")
        if "bufferView" not in accessor:
            return
        view_number = self.index(accessor["bufferView"], f"{what} bufferView", "bufferViews")
        view = self.items("bufferViews")[view_number]
        offset = self.integer(accessor.get("byteOffset", 0), f"{what} byteOffset")
        element = _COMPONENT_BYTES[component] * _TYPE_SIZE[accessor["type"]]
        stride = view.get("byteStride", element)
        end = offset + stride * (count - 1) + element
        if end > view["byteLength"]:
            self.fail(f"{what} needs {end} bytes of bufferView {view_number}, which has {view['byteLength']}")

    def values(self, number: int) -> np.ndarray:
        """An accessor's data as (count, components) (checked by `accessor` first)."""
        accessor = self.items("accessors")[number]
        components = _TYPE_SIZE[accessor["type"]]
        if "bufferView" not in accessor:
            return np.zeros((accessor["count"], components))
        dtype = np.dtype(_COMPONENT_DTYPE[accessor["componentType"]])
        view = self.items("bufferViews")[accessor["bufferView"]]
        element = dtype.itemsize * components
        stride = view.get("byteStride", element)
        data = self.view_bytes(accessor["bufferView"])[accessor.get("byteOffset", 0):]
        rows = np.lib.stride_tricks.as_strided(np.frombuffer(data, np.uint8), (accessor["count"], element),
                                               (stride, 1))
        return np.ascontiguousarray(rows).view(dtype).reshape(accessor["count"], components)

    def primitive(self, primitive: dict, what: str) -> None:
        attributes = primitive.get("attributes")
        if not isinstance(attributes, dict) or "POSITION" not in attributes:
            self.fail(f"{what} has no POSITION attribute")
        counts = {self.items("accessors")[self.index(a, f"{what} {name}", "accessors")]["count"]
                  for name, a in attributes.items()}
        if len(counts) != 1:
            self.fail(f"{what}: its attributes have different counts ({', '.join(map(str, sorted(counts)))})")
        mode = primitive.get("mode", 4)
        if mode not in range(7):
            self.fail(f"{what} mode {json.dumps(mode)[:20]} is not a glTF primitive mode")
        self.declared_range(attributes["POSITION"], f"{what} POSITION")
        if "indices" in primitive:
            indices = self.index(primitive["indices"], f"{what} indices", "accessors")
            accessor = self.items("accessors")[indices]
            if accessor["type"] != "SCALAR" or accessor["componentType"] not in (5121, 5123, 5125):
                self.fail(f"{what} indices are not unsigned whole numbers (SCALAR, unsigned byte/short/int)")
            values = self.values(indices)
            if len(values) and int(values.max()) >= counts.pop():
                self.fail(f"{what} indices name vertex {int(values.max())}, past its "
                          f"{self.items('accessors')[attributes['POSITION']]['count']} vertices")

    def declared_range(self, number: int, what: str) -> None:
        """The data lie within the accessor's declared min/max (which glTF requires for POSITION):
        overwritten offsets or bytes show up here."""
        accessor = self.items("accessors")[number]
        values = self.values(number).astype(np.float64)
        if not np.isfinite(values).all():
            self.fail(f"{what} contains NaN or infinity")
        for key, bad in (("min", values.min(axis=0)), ("max", values.max(axis=0))):
            declared = accessor.get(key)
            if declared is None:
                continue
            if not isinstance(declared, list) or len(declared) != values.shape[1] or not all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) for v in declared):
                self.fail(f"{what} {key} is not {values.shape[1]} numbers")
            declared = np.asarray(declared, dtype=np.float64)
            tolerance = 1e-4 * np.maximum(1.0, np.abs(declared))
            outside = bad < declared - tolerance if key == "min" else bad > declared + tolerance
            if outside.any():
                self.fail(f"{what} data lie outside the accessor's declared {key} (corrupt data or offsets)")

    def images(self, base: Path) -> list[tuple[str, bytes | None]]:
        """Each image's (name, encoded bytes); None for an external file that is missing."""
        result = []
        for number, image in enumerate(self.items("images")):
            name = f"{self.path}: image {number}"
            if "bufferView" in image:
                result.append((name, self.view_bytes(self.index(image["bufferView"], f"image {number} bufferView",
                                                                "bufferViews"))))
            elif isinstance(image.get("uri"), str):
                result.append((f"{name} ('{image['uri'][:60]}')",
                               self.uri(image["uri"], f"image {number}", base, optional=True)))
            else:
                self.fail(f"image {number} has neither a bufferView nor a uri")
        return result

    def uri(self, uri: str, what: str, base: Path, optional: bool = False) -> bytes | None:
        """The bytes a uri names, as trimesh reads them: base64 data after 'base64,', else the file of
        exactly that name in the glTF's folder (regular files only; trimesh would fall back to another
        file of the same base name). None for a missing file when `optional`."""
        if "base64," in uri:
            try:
                return base64.b64decode(uri[uri.index("base64,") + 7:], validate=True)
            except (binascii.Error, ValueError):
                self.fail(f"{what}: malformed base64 data URI")
        if re.match(r"[A-Za-z][A-Za-z0-9+.-]+:", uri):
            self.fail(f"{what}: uri '{uri[:60]}' is not a file beside the glTF; only those are read")
        root = resolved(base, "folder")
        target = resolved(root / uri.strip(), f"file ({what} of {self.path.name})")
        if not target.is_relative_to(root):
            self.fail(f"{what}: uri '{uri[:60]}' leads outside the glTF's folder; only files in it are read")
        if optional and not os.path.lexists(target):
            return None
        return read_regular(target, f"file ({what} of {self.path.name})")


def _json(path: Path, text: bytes, where: str):
    try:
        return json.loads(text.decode("utf-8"))
    except UnicodeDecodeError:
        raise MeshError(f"{path}: {where} is not UTF-8 text") from None
    except (ValueError, RecursionError) as error:
        raise MeshError(f"{path}: {where} is not valid JSON ({str(error)[:80]})") from None


def check_glb(path: Path, data: bytes) -> list[tuple[str, bytes | None]]:
    """The GLB container (magic, version 2, total length, JSON chunk, optional BIN chunk) and the
    document in it (see `_Gltf`). Returns the embedded images for `check_images`."""
    if len(data) < 20 or data[:4] != b"glTF":
        raise MeshError(f"{path}: not a GLB file (no 'glTF' magic)")
    version, length = struct.unpack_from("<II", data, 4)
    if version != 2:
        raise MeshError(f"{path}: GLB version {version}; only glTF 2.0 is read")
    if length != len(data):
        raise MeshError(f"{path}: the GLB header says {length} bytes, the file has {len(data)} (cut off?)")
    chunks, offset = [], 12
    while offset < len(data):
        if offset + 8 > len(data):
            raise MeshError(f"{path}: cut off inside a GLB chunk header at byte {offset}")
        size, kind = struct.unpack_from("<I4s", data, offset)
        if offset + 8 + size > len(data):
            raise MeshError(f"{path}: GLB chunk at byte {offset} promises {size} bytes past the end of the file")
        chunks.append((kind, data[offset + 8:offset + 8 + size]))
        offset += 8 + size
    if not chunks or chunks[0][0] != b"JSON":
        raise MeshError(f"{path}: the first GLB chunk is not JSON")
    document = _json(path, chunks[0][1], "the GLB's JSON chunk")
    binary = chunks[1][1] if len(chunks) > 1 and chunks[1][0] == b"BIN\x00" else None
    buffers = []
    checker = _Gltf(path, document, buffers)
    if isinstance(document, dict):
        for number, buffer in enumerate(checker.items("buffers")):
            buffers.append(binary if number == 0 and "uri" not in buffer else
                           checker.uri(buffer["uri"], f"buffer {number}", path.parent)
                           if isinstance(buffer.get("uri"), str) else None)
    checker.check()
    return checker.images(path.parent)


def check_gltf(path: Path, data: bytes) -> list[tuple[str, bytes | None]]:
    """A .gltf document, its buffer files or data URIs (regular files only), see `_Gltf`. Returns the
    images for `check_images` (None for a missing image file: a warning, like a missing OBJ texture)."""
    document = _json(path, data, "the glTF file")
    checker = _Gltf(path, document, [])
    if isinstance(document, dict):
        for number, buffer in enumerate(checker.items("buffers")):
            if not isinstance(buffer.get("uri"), str):
                checker.fail(f"buffer {number} has no uri (a .gltf keeps its data in files or data URIs)")
            checker.buffers.append(checker.uri(buffer["uri"], f"buffer {number}", path.parent))
    checker.check()
    return checker.images(path.parent)


def check_images(images: list[tuple[str, bytes | Path | None]]) -> None:
    """Every texture present decodes fully (a corrupt one would silently become a flat colour)."""
    for name, source in images:
        if source is not None:
            read_image(source, name)
