"""Write the hostile-input corpus (issue #14): broken files of every format meshseal reads, a few valid
controls, and the command runs to try on each.

Everything is generated (standard library, numpy, PIL, trimesh and meshseal itself); nothing binary is
committed. `build(root)` writes the files under `root` and returns the runs, each a dict:
  id, group, case, cls (the class counted in the closing note), argv (for meshseal.cli.main),
  expect ('error': exit 2 with one `meshseal: error:` line; 'ok': exit 0; 'any': either, for multi-picture
  calls), watch (the case's input folder: nothing in it may change), out (the folder outputs go to),
  outputs (files an 'ok' run must leave in `out`).
Run `python tests/corpus_gen.py DIR` to write it and print the case counts per class.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import struct
import sys
import zlib
from pathlib import Path

import numpy as np
from PIL import Image, PngImagePlugin

MESSAGE = "01" * 32  # the default model's 64 bits
CAMERA_KEY = "meshseal:camera"


# ---------------------------------------------------------------- valid bases


def _sphere():
    """A small textured sphere (42 vertices, 80 faces), spherical UVs, a 64x64 colour texture."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=1)
    v = mesh.vertices
    uv = np.c_[0.5 + np.arctan2(v[:, 1], v[:, 0]) / (2 * np.pi), 0.5 + np.arcsin(np.clip(v[:, 2], -1, 1)) / np.pi]
    y, x = np.mgrid[0:64, 0:64]
    pixels = np.stack([(x * 4) % 256, (y * 4) % 256, ((x ^ y) * 8) % 256], axis=-1).astype(np.uint8)
    texture = Image.fromarray(pixels)
    return v, np.asarray(mesh.faces), np.asarray(mesh.vertex_normals), uv, texture


def _png(image: Image.Image, **options) -> bytes:
    buffer = io.BytesIO()
    image.save(buffer, format="PNG", **options)
    return buffer.getvalue()


def _encode(image: Image.Image, fmt: str, **options) -> bytes:
    buffer = io.BytesIO()
    image.save(buffer, format=fmt, **options)
    return buffer.getvalue()


def _bases() -> dict[str, bytes | str]:
    import trimesh

    v, f, n, uv, texture = _sphere()
    fmt = lambda row: " ".join(f"{x:.6f}" for x in row)  # noqa: E731
    obj = ("mtllib skin.mtl\nusemtl skin\n" + "".join(f"v {fmt(p)}\n" for p in v) + "".join(f"vt {fmt(t)}\n" for t in uv)
           + "".join(f"vn {fmt(q)}\n" for q in n)
           + "".join("f " + " ".join(f"{i + 1}/{i + 1}/{i + 1}" for i in face) + "\n" for face in f))
    ply = ("ply\nformat ascii 1.0\ncomment meshseal corpus\nelement vertex %d\nproperty float x\nproperty float y\n"
           "property float z\nelement face %d\nproperty list uchar int vertex_indices\nend_header\n" % (len(v), len(f))
           + "".join(f"{fmt(p)}\n" for p in v) + "".join("3 " + " ".join(map(str, face)) + "\n" for face in f))
    off = (f"OFF\n# meshseal corpus\n{len(v)} {len(f)} 0\n" + "".join(f"{fmt(p)}\n" for p in v)
           + "".join("3 " + " ".join(map(str, face)) + "\n" for face in f))
    plain = trimesh.Trimesh(v, f, process=False)
    textured = trimesh.Trimesh(v, f, vertex_normals=n, process=False,
                               visual=trimesh.visual.TextureVisuals(uv=uv, image=texture))
    gltf = trimesh.exchange.gltf.export_gltf(trimesh.Scene(textured), include_normals=True, embed_buffers=False)
    return {
        "obj": obj, "mtl": "newmtl skin\nKd 1 1 1\nmap_Kd skin.png\n", "png": _png(texture),
        "jpg": _encode(texture, "JPEG", quality=90), "ply": ply,
        "ply_bin": trimesh.exchange.ply.export_ply(plain, encoding="binary"), "off": off,
        "stl": trimesh.exchange.stl.export_stl(plain), "stl_ascii": trimesh.exchange.stl.export_stl_ascii(plain),
        "glb": trimesh.exchange.gltf.export_glb(trimesh.Scene(textured), include_normals=True),
        "gltf": gltf,
    }


# ---------------------------------------------------------------- helpers


def _glb_parts(data: bytes) -> tuple[dict, bytes]:
    length = struct.unpack_from("<I", data, 12)[0]
    json_end = 20 + length
    return json.loads(data[20:json_end]), data[json_end + 8:]


def _glb(document: dict, binary: bytes) -> bytes:
    body = json.dumps(document).encode()
    body += b" " * (-len(body) % 4)
    binary += b"\0" * (-len(binary) % 4)
    chunks = struct.pack("<I4s", len(body), b"JSON") + body + struct.pack("<I4s", len(binary), b"BIN\0") + binary
    return b"glTF" + struct.pack("<II", 2, 12 + len(chunks)) + chunks


def _edit(document: dict, change) -> dict:
    copy = json.loads(json.dumps(document))
    change(copy)
    return copy


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _bomb_png(width: int = 100_000, height: int = 100_000) -> bytes:
    """A PNG header claiming width x height pixels over a few bytes of data."""
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", header) + _png_chunk(b"IDAT", zlib.compress(b"\0" * 64))
            + _png_chunk(b"IEND", b""))


def _cuts(data: bytes, start: int, count: int) -> list[int]:
    """`count` cut positions spread over data[start:]."""
    return sorted({int(p) for p in np.linspace(start, len(data) - 1, count + 2)[1:-1]})


def _line_cuts(text: str, prefix: str, count: int) -> list[int]:
    """Cut positions inside records starting with `prefix` (after its first word), never at a line end."""
    positions = []
    offset = 0
    for line in text.splitlines(keepends=True):
        if line.startswith(prefix):
            positions.append(offset + len(line.rstrip()) - 1)
        offset += len(line)
    picks = np.linspace(0, len(positions) - 1, count).astype(int)
    return sorted({positions[i] for i in picks})


class Corpus:
    """Collects cases and the runs to try on them."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.runs: list[dict] = []
        self.cases: dict[str, tuple[str, bool]] = {}  # case -> (class, hostile)
        self.reference: Path | None = None  # the valid render the pictures are made from
        self.odd_pictures: dict[str, bytes] = {}  # valid pictures in other formats (see test_corpus.py)

    def folder(self, group: str, case: str) -> Path:
        folder = self.root / group / case
        folder.mkdir(parents=True, exist_ok=False)
        return folder

    def files(self, group: str, case: str, files: dict[str, bytes | str]) -> Path:
        folder = self.folder(group, case)
        for name, data in files.items():
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            (folder / name).write_bytes(data.encode() if isinstance(data, str) else data)
        return folder

    def run(self, group: str, case: str, cls: str, command: str, argv: list, expect: str, watch: Path,
            outputs: tuple[str, ...] = (), hostile: bool = True) -> None:
        out = self.root / "_out" / group / case / command
        argv = [str(a).replace("{out}", str(out)) for a in argv]
        self.cases[f"{group}/{case}"] = (cls, hostile)
        self.runs.append({"id": f"{group}/{case}/{command}", "group": group, "case": case, "cls": cls, "argv": argv,
                          "expect": expect, "watch": str(watch), "out": str(out), "outputs": list(outputs)})

    def mesh(self, group: str, case: str, cls: str, files: dict, main: str, expect: str = "error",
             embed: str | None = None) -> Path:
        """A mesh case tried with info, render and embed. `expect` is for reading it ('error' or 'ok');
        `embed` overrides the embed expectation (an untextured mesh cannot carry the default model's mark)."""
        folder = self.files(group, case, files) if files is not None else self.folder(group, case)
        path = folder / main
        suffix = Path(main).suffix
        hostile = expect == "error"
        self.run(group, case, cls, "info", ["info", path], expect, folder, hostile=hostile)
        self.run(group, case, cls, "render", ["render", path, "-o", "{out}/view.png", "--width", 32, "--height", 32],
                 expect, folder, ("view.png",), hostile)
        embed = embed or expect
        self.run(group, case, cls, "embed", ["embed", path, "-o", f"{{out}}/marked{suffix}", "--bits", MESSAGE,
                                             "--views", 1], embed, folder, (f"marked{suffix}",), hostile)
        return folder


# ---------------------------------------------------------------- cases per format


def _obj_cases(c: Corpus, base: dict) -> None:
    obj, mtl, png = base["obj"], base["mtl"], base["png"]
    good = {"skin.mtl": mtl, "skin.png": png}
    c.mesh("obj", "valid", "control", {"sphere.obj": obj, **good}, "sphere.obj", "ok")
    c.mesh("obj", "valid_latin1_comment", "control", {"sphere.obj": "# caf\xe9\n".encode("latin-1") + obj.encode(), **good},
           "sphere.obj", "ok")
    c.mesh("obj", "missing_texture", "documented recovery", {"sphere.obj": obj, "skin.mtl": mtl}, "sphere.obj", "ok",
           embed="error")
    c.mesh("obj", "missing_mtl", "documented recovery", {"sphere.obj": obj}, "sphere.obj", "ok", embed="error")
    for k, cut in enumerate(_line_cuts(obj, "f ", 8)):
        text = obj[:cut]
        if len(text.splitlines()[-1].split()) >= 4:  # still 3 whole corners: not a detectable cut
            text = text[: text.rindex(" ")]
        c.mesh("obj", f"cut_in_face_{k}", "truncated", {"sphere.obj": text, **good}, "sphere.obj")
    for k, cut in enumerate(_line_cuts(obj, "v ", 3)):
        c.mesh("obj", f"cut_in_vertex_{k}", "truncated", {"sphere.obj": obj[:obj.rindex(" ", 0, cut)] + "\nf 1 2 3\n",
                                                          **good}, "sphere.obj")
    tri = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nvn 0 0 1\n"
    faces = {
        "index_zero_v": "f 0 1 2", "index_zero_vt": "f 1/0 2/2 3/3", "index_zero_vn": "f 1//0 2//1 3//1",
        "v_past_end": "f 1 2 4", "vt_past_end": "f 1/1 2/2 3/9", "vn_past_end": "f 1//1 2//1 3//5",
        "negative_past_start": "f -1 -2 -4", "negative_vt_past_start": "f 1/-4 2/1 3/2",
        "negative_vn_past_start": "f 1//-2 2//1 3//1", "huge_index": "f 1 2 99999999999999999999",
        "two_corners": "f 1 2", "one_corner": "f 1", "empty_face": "f", "text_index": "f a b c",
        "float_index": "f 1.5 2 3", "four_slashes": "f 1/1/1/1 2/2/2 3/3/3", "missing_v_index": "f /1 /2 /3",
    }
    for name, face in faces.items():
        c.mesh("obj", name, "bad index", {"tri.obj": tri + face + "\n"}, "tri.obj")
    records = {"v_two_numbers": "v 0 0\n", "v_text": "v 0 zero 0\n", "v_eight_numbers": "v 0 0 0 1 1 1 1 1\n",
               "vt_no_numbers": "vt\n", "vt_text": "vt u v\n", "vn_two_numbers": "vn 0 1\n", "vn_text": "vn x y z\n"}
    for name, record in records.items():
        c.mesh("obj", name, "bad record", {"tri.obj": record + tri + "f 1 2 3\n"}, "tri.obj")
    c.mesh("obj", "nan_vertex", "bad record", {"tri.obj": tri.replace("v 0 1 0", "v nan 1 0") + "f 1 2 3\n"}, "tri.obj")
    c.mesh("obj", "inf_vertex", "bad record", {"tri.obj": tri.replace("v 0 1 0", "v 0 inf 0") + "f 1 2 3\n"}, "tri.obj")
    c.mesh("obj", "no_faces", "bad structure", {"tri.obj": tri}, "tri.obj")
    c.mesh("obj", "comments_only", "bad structure", {"tri.obj": "# nothing\n# here\n"}, "tri.obj")
    c.mesh("obj", "empty", "empty or garbage", {"tri.obj": ""}, "tri.obj")
    c.mesh("obj", "binary_garbage", "empty or garbage", {"tri.obj": np.random.default_rng(1).bytes(3000)}, "tri.obj")
    c.mesh("obj", "nul_in_text", "empty or garbage", {"tri.obj": tri + "\0\0\0f 1 2 3\n"}, "tri.obj")
    c.mesh("obj", "png_named_obj", "empty or garbage", {"tri.obj": png}, "tri.obj")
    # Textures and material files.
    textured = {"sphere.obj": obj, "skin.mtl": mtl}
    variants = {
        "texture_truncated_png": png[: len(png) // 2], "texture_truncated_jpg": base["jpg"][: len(base["jpg"]) // 2],
        "texture_empty": b"", "texture_text": "not a picture\n", "texture_bomb": _bomb_png(),
        "texture_png_bad_crc": png[:40] + bytes([png[40] ^ 0xFF]) + png[41:],
        "texture_header_only": png[:33],
    }
    for name, data in variants.items():
        c.mesh("obj", name, "broken texture", {**textured, "skin.png": data}, "sphere.obj")
    c.mesh("obj", "mtl_binary_garbage_texture_fine", "documented recovery",
           {"sphere.obj": obj, "skin.mtl": mtl + "\n" + "\xff\xfe garbage\n", "skin.png": png}, "sphere.obj", "ok")


def _ply_cases(c: Corpus, base: dict) -> None:
    ply, ply_bin = base["ply"], base["ply_bin"]
    c.mesh("ply", "valid_ascii", "control", {"m.ply": ply}, "m.ply", "ok", embed="error")
    c.mesh("ply", "valid_binary", "control", {"m.ply": ply_bin}, "m.ply", "ok", embed="error")
    body = ply.index("end_header") + 11
    for k, cut in enumerate(_cuts(ply.encode(), body + 5, 10)):
        c.mesh("ply", f"ascii_cut_{k}", "truncated", {"m.ply": ply[:cut]}, "m.ply")
    body_bin = ply_bin.index(b"end_header") + 11
    for k, cut in enumerate(_cuts(ply_bin, body_bin + 1, 6)):
        c.mesh("ply", f"binary_cut_{k}", "truncated", {"m.ply": ply_bin[:cut]}, "m.ply")
    c.mesh("ply", "header_only", "truncated", {"m.ply": ply[:body]}, "m.ply")
    c.mesh("ply", "cut_in_header", "truncated", {"m.ply": ply[:40]}, "m.ply")
    counts = {"more_faces": ("element face 80", "element face 90"), "fewer_faces": ("element face 80", "element face 70"),
              "more_vertices": ("element vertex 42", "element vertex 50"),
              "fewer_vertices": ("element vertex 42", "element vertex 40")}
    for name, (old, new) in counts.items():
        c.mesh("ply", f"ascii_{name}", "header counts", {"m.ply": ply.replace(old, new)}, "m.ply")
        c.mesh("ply", f"binary_{name}", "header counts", {"m.ply": ply_bin.replace(old.encode(), new.encode())}, "m.ply")
    formats = {"format_banana": "format banana 1.0", "format_version_2": "format ascii 2.0",
               "format_middle_endian": "format binary_middle_endian 1.0", "format_missing": "comment no format",
               "format_no_version": "format ascii"}
    for name, line in formats.items():
        c.mesh("ply", name, "bad header", {"m.ply": ply.replace("format ascii 1.0", line)}, "m.ply")
    headers = {
        "unknown_type": ("property float x", "property float128 x"),
        "property_before_element": ("ply\nformat ascii 1.0\n", "ply\nformat ascii 1.0\nproperty float w\n"),
        "negative_count": ("element face 80", "element face -80"),
        "text_count": ("element face 80", "element face many"),
        "unknown_keyword": ("comment meshseal corpus", "colour red"),
        "no_end_header": ("end_header\n", "end_headr\n"),
        "list_without_types": ("property list uchar int vertex_indices", "property list vertex_indices"),
    }
    for name, (old, new) in headers.items():
        c.mesh("ply", name, "bad header", {"m.ply": ply.replace(old, new, 1)}, "m.ply")
    lines = ply.splitlines(keepends=True)
    last = len(lines) - 1
    records = {
        "list_count_too_big": lines[:last] + ["4 0 1 2\n"], "list_count_text": lines[:last] + ["x 0 1 2\n"],
        "extra_record": lines + ["3 0 1 2\n"], "vertex_missing_value": [l if l != lines[12] else "0.5 0.5\n" for l in lines],
        "index_out_of_range": lines[:last] + ["3 0 1 420\n"], "value_text": lines[:12] + ["0.1 zero 0.2\n"] + lines[13:],
        "nan_vertex": lines[:12] + ["nan 0 0\n"] + lines[13:],
    }
    for name, record_lines in records.items():
        c.mesh("ply", name, "bad record", {"m.ply": "".join(record_lines)}, "m.ply")
    c.mesh("ply", "empty", "empty or garbage", {"m.ply": b""}, "m.ply")
    c.mesh("ply", "garbage", "empty or garbage", {"m.ply": np.random.default_rng(2).bytes(2000)}, "m.ply")
    c.mesh("ply", "magic_only", "empty or garbage", {"m.ply": "ply\n"}, "m.ply")


def _off_cases(c: Corpus, base: dict) -> None:
    off = base["off"]
    c.mesh("off", "valid", "control", {"m.off": off}, "m.off", "ok", embed="error")
    c.mesh("off", "valid_counts_on_keyword_line", "control", {"m.off": off.replace("OFF\n# meshseal corpus\n", "OFF ")},
           "m.off", "ok", embed="error")
    start = off.index(" 0\n") + 3
    for k, cut in enumerate(_cuts(off.encode(), start + 5, 10)):
        c.mesh("off", f"cut_{k}", "truncated", {"m.off": off[:cut]}, "m.off")
    c.mesh("off", "header_only", "truncated", {"m.off": off[:start]}, "m.off")
    counts = {"more_faces": "42 90 0", "fewer_faces": "42 70 0", "more_vertices": "50 80 0", "fewer_vertices": "40 80 0",
              "count_text": "42 many 0", "count_negative": "42 -80 0", "one_count": "42", "no_counts": ""}
    for name, line in counts.items():
        c.mesh("off", name, "header counts", {"m.off": off.replace("42 80 0", line, 1)}, "m.off")
    c.mesh("off", "keyword_4off", "bad header", {"m.off": off.replace("OFF", "4OFF", 1)}, "m.off")
    c.mesh("off", "keyword_missing", "bad header", {"m.off": off.replace("OFF\n", "", 1)}, "m.off")
    lines = off.splitlines(keepends=True)
    last = len(lines) - 1
    records = {"two_corners": lines[:last] + ["2 0 1\n"], "count_past_indices": lines[:last] + ["5 0 1 2\n"],
               "index_out_of_range": lines[:last] + ["3 0 1 42\n"], "negative_index": lines[:last] + ["3 0 -1 2\n"],
               "text_index": lines[:last] + ["3 0 one 2\n"], "vertex_two_numbers": lines[:3] + ["0.5 0.5\n"] + lines[4:],
               "vertex_text": lines[:3] + ["x y z\n"] + lines[4:], "extra_line": lines + ["3 0 1 2\n"],
               "inf_vertex": lines[:3] + ["inf 0 0\n"] + lines[4:]}
    for name, record_lines in records.items():
        c.mesh("off", name, "bad record", {"m.off": "".join(record_lines)}, "m.off")
    c.mesh("off", "empty", "empty or garbage", {"m.off": b""}, "m.off")
    c.mesh("off", "garbage", "empty or garbage", {"m.off": np.random.default_rng(3).bytes(2000)}, "m.off")


def _stl_cases(c: Corpus, base: dict) -> None:
    stl, ascii_stl = base["stl"], base["stl_ascii"]
    c.mesh("stl", "valid_binary", "control", {"m.stl": stl}, "m.stl", "ok", embed="error")
    c.mesh("stl", "valid_ascii", "control", {"m.stl": ascii_stl}, "m.stl", "ok", embed="error")
    for k, cut in enumerate(_cuts(stl, 85, 6)):
        c.mesh("stl", f"binary_cut_{k}", "truncated", {"m.stl": stl[:cut]}, "m.stl")
    c.mesh("stl", "binary_header_cut", "truncated", {"m.stl": stl[:50]}, "m.stl")
    c.mesh("stl", "binary_count_more", "header counts", {"m.stl": stl[:80] + struct.pack("<I", 81) + stl[84:]}, "m.stl")
    c.mesh("stl", "binary_count_fewer", "header counts", {"m.stl": stl[:80] + struct.pack("<I", 79) + stl[84:]}, "m.stl")
    c.mesh("stl", "binary_zero_triangles", "bad structure", {"m.stl": stl[:80] + struct.pack("<I", 0)}, "m.stl")
    for k, cut in enumerate(_cuts(ascii_stl.encode(), 20, 6)):
        c.mesh("stl", f"ascii_cut_{k}", "truncated", {"m.stl": ascii_stl[:cut]}, "m.stl")
    facet_lines = ascii_stl.splitlines(keepends=True)
    vertex = next(i for i, l in enumerate(facet_lines) if l.strip().startswith("vertex"))
    records = {"two_vertices": facet_lines[:vertex] + facet_lines[vertex + 1:],
               "four_vertices": facet_lines[:vertex] + [facet_lines[vertex]] + facet_lines[vertex:],
               "vertex_text": facet_lines[:vertex] + ["vertex a b c\n"] + facet_lines[vertex + 1:],
               "vertex_nan": facet_lines[:vertex] + ["vertex nan 0 0\n"] + facet_lines[vertex + 1:],
               "no_endloop": [l for i, l in enumerate(facet_lines) if not (l.strip() == "endloop" and i < vertex + 5)],
               "unknown_word": facet_lines[:vertex] + ["colour 1 0 0\n"] + facet_lines[vertex:]}
    for name, record_lines in records.items():
        c.mesh("stl", f"ascii_{name}", "bad record", {"m.stl": "".join(record_lines)}, "m.stl")
    c.mesh("stl", "empty", "empty or garbage", {"m.stl": b""}, "m.stl")
    c.mesh("stl", "garbage", "empty or garbage", {"m.stl": np.random.default_rng(4).bytes(1999)}, "m.stl")


def _gltf_cases(c: Corpus, base: dict) -> None:
    glb = base["glb"]
    document, binary = _glb_parts(glb)
    c.mesh("gltf", "valid_glb", "control", {"m.glb": glb}, "m.glb", "ok")
    for k, cut in enumerate(_cuts(glb, 13, 7)):
        c.mesh("gltf", f"glb_cut_{k}", "truncated", {"m.glb": glb[:cut]}, "m.glb")
    json_length = struct.unpack_from("<I", glb, 12)[0]
    for k, at in enumerate(np.linspace(21, 20 + json_length - 4, 8).astype(int)):
        data = bytearray(glb)
        data[at:at + 3] = b"\x00#\x01"
        c.mesh("gltf", f"glb_json_overwritten_{k}", "corrupt container", {"m.glb": bytes(data)}, "m.glb")
    container = {"glb_length_wrong": glb[:8] + struct.pack("<I", len(glb) + 40) + glb[12:],
                 "glb_version_1": glb[:4] + struct.pack("<I", 1) + glb[8:], "glb_magic": b"gLTF" + glb[4:],
                 "glb_json_chunk_type": glb[:16] + b"JSOX" + glb[20:],
                 "glb_chunk_past_end": glb[:12] + struct.pack("<I", json_length + 10_000) + glb[16:],
                 "glb_padded": glb + b"\0" * 8}
    for name, data in container.items():
        c.mesh("gltf", name, "corrupt container", {"m.glb": data}, "m.glb")
    position = document["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
    indices = document["meshes"][0]["primitives"][0]["indices"]

    def accessor(key, value, number=position):
        return lambda d: d["accessors"][number].__setitem__(key, value)

    edits = {
        "accessor_negative_count": accessor("count", -3), "accessor_zero_count": accessor("count", 0),
        "accessor_count_past_view": accessor("count", 4000), "accessor_count_text": accessor("count", "42"),
        "accessor_offset_past_view": accessor("byteOffset", 1 << 20), "accessor_component_type": accessor("componentType", 5130),
        "accessor_type": accessor("type", "VEC5"), "accessor_view_missing": accessor("bufferView", 99),
        "indices_count_past_view": accessor("count", 100_000, indices), "indices_float": accessor("componentType", 5126, indices),
        "view_past_buffer": lambda d: d["bufferViews"][0].__setitem__("byteLength", 1 << 24),
        "view_negative_offset": lambda d: d["bufferViews"][0].__setitem__("byteOffset", -4),
        "view_odd_stride": lambda d: d["bufferViews"][1].__setitem__("byteStride", 6),
        "view_buffer_missing": lambda d: d["bufferViews"][0].__setitem__("buffer", 3),
        "buffer_longer_than_bin": lambda d: d["buffers"][0].__setitem__("byteLength", len(binary) + 4096),
        "buffer_missing_file": lambda d: d["buffers"][0].__setitem__("uri", "nowhere.bin"),
        "node_cycle": lambda d: d["nodes"].extend([{"children": [len(d["nodes"]) + 1]}, {"children": [len(d["nodes"])]}]),
        "node_child_missing": lambda d: d["nodes"][0].__setitem__("children", [42]),
        "node_mesh_missing": lambda d: d["nodes"][0].__setitem__("mesh", 7),
        "node_matrix_short": lambda d: d["nodes"][0].__setitem__("matrix", [1, 0, 0]),
        "node_two_parents": lambda d: d["nodes"].extend([{"children": [0]}, {"children": [0]}]),
        "scene_node_missing": lambda d: d["scenes"][0].__setitem__("nodes", [5]),
        "primitive_no_position": lambda d: d["meshes"][0]["primitives"][0]["attributes"].pop("POSITION"),
        "primitive_mode": lambda d: d["meshes"][0]["primitives"][0].__setitem__("mode", 9),
        "primitive_no_list": lambda d: d["meshes"][0].__setitem__("primitives", []),
        "attribute_counts_differ": lambda d: d["accessors"][position].__setitem__("count", d["accessors"][position]["count"] - 1),
        "draco_required": lambda d: d.__setitem__("extensionsRequired", ["KHR_draco_mesh_compression"]),
        "asset_version_1": lambda d: d["asset"].__setitem__("version", "1.0"),
        "texture_source_missing": lambda d: d["textures"][0].__setitem__("source", 4),
        "material_texture_missing": lambda d: d["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"].__setitem__("index", 9),
        "image_no_source": lambda d: d["images"][0].pop("bufferView"),
        "accessors_not_list": lambda d: d.__setitem__("accessors", {"0": 1}),
    }
    for name, change in edits.items():
        c.mesh("gltf", name, "bad document", {"m.glb": _glb(_edit(document, change), binary)}, "m.glb")
    c.mesh("gltf", "json_not_object", "bad document", {"m.glb": _glb([1, 2, 3], binary)}, "m.glb")  # type: ignore[arg-type]
    # Binary data: positions, indices and the embedded image overwritten.
    views = document["bufferViews"]

    def overwrite(view: int, offset: int, data: bytes) -> bytes:
        start = views[view].get("byteOffset", 0) + offset
        return binary[:start] + data + binary[start + len(data):]

    position_view = document["accessors"][position]["bufferView"]
    index_view = document["accessors"][indices]["bufferView"]
    image_view = document["images"][0]["bufferView"]
    data_edits = {"positions_overwritten": overwrite(position_view, 12, struct.pack("<3f", 1e6, -1e6, 1e6)),
                  "positions_nan": overwrite(position_view, 0, struct.pack("<f", float("nan"))),
                  "indices_past_vertices": overwrite(index_view, 0, struct.pack("<I", 4242)),
                  "image_overwritten": overwrite(image_view, 60, b"\0" * 400),
                  "image_bomb": None}
    for name, data in data_edits.items():
        if data is None:
            bomb = _bomb_png()
            start = views[image_view].get("byteOffset", 0)
            data = binary[:start] + bomb + b"\0" * (views[image_view]["byteLength"] - len(bomb)) + binary[start + views[image_view]["byteLength"]:]
        c.mesh("gltf", name, "bad binary data", {"m.glb": _glb(document, data)}, "m.glb")
    # .gltf with external files.
    files = dict(base["gltf"])
    model = json.loads(files.pop("model.gltf"))
    bin_name = model["buffers"][0]["uri"]
    c.mesh("gltf", "valid_gltf", "control", {"m.gltf": json.dumps(model), **files}, "m.gltf", "ok")
    gltf_edits = {
        "gltf_buffer_missing": (lambda d: None, {bin_name: None}),
        "gltf_buffer_short": (lambda d: None, {bin_name: files[bin_name][:-100]}),
        "gltf_buffer_escapes_folder": (lambda d: d["buffers"][0].__setitem__("uri", "../" + bin_name), {}),
        "gltf_buffer_url": (lambda d: d["buffers"][0].__setitem__("uri", "https://example.invalid/" + bin_name), {}),
        "gltf_buffer_bad_base64": (lambda d: d["buffers"][0].__setitem__("uri", "data:application/octet-stream;base64,@@@"), {}),
        "gltf_buffer_no_uri": (lambda d: d["buffers"][0].pop("uri"), {}),
        "gltf_accessor_negative_count": (accessor("count", -1), {}),
        "gltf_image_corrupt": (lambda d: d["images"].append({"uri": "broken.png"}) or d["textures"][0].__setitem__("source", 1),
                               {"broken.png": base["png"][:200]}),
        "gltf_image_bomb": (lambda d: d["images"].append({"uri": "bomb.png"}) or d["textures"][0].__setitem__("source", 1),
                            {"bomb.png": _bomb_png()}),
    }
    for name, (change, replace) in gltf_edits.items():
        case_files = {"m.gltf": json.dumps(_edit(model, change)), **files}
        for key, value in replace.items():
            if value is None:
                case_files.pop(key)
            else:
                case_files[key] = value
        c.mesh("gltf", name, "bad document" if "buffer" in name or "accessor" in name else "broken texture",
               case_files, "m.gltf")
    c.mesh("gltf", "gltf_truncated_json", "truncated", {"m.gltf": json.dumps(model)[:300], **files}, "m.gltf")
    c.mesh("gltf", "gltf_image_missing", "documented recovery",
           {"m.gltf": json.dumps(_edit(model, lambda d: d["images"].append({"uri": "gone.png"})
                                       or d["textures"][0].__setitem__("source", 1))), **files}, "m.gltf", "ok",
           embed="error")


def _special_cases(c: Corpus, base: dict) -> None:
    """Named pipes, devices, folders and links where a file is expected: refused at once, never opened."""
    for suffix in ("obj", "glb", "ply", "off", "stl", "gltf"):
        folder = c.folder("special", f"mesh_fifo_{suffix}")
        os.mkfifo(folder / f"m.{suffix}")
        _mesh_runs(c, "special", f"mesh_fifo_{suffix}", folder, f"m.{suffix}")
    folder = c.folder("special", "mesh_device")
    os.symlink("/dev/zero", folder / "m.stl")
    _mesh_runs(c, "special", "mesh_device", folder, "m.stl")
    folder = c.folder("special", "mesh_is_folder")
    (folder / "m.obj").mkdir()
    _mesh_runs(c, "special", "mesh_is_folder", folder, "m.obj")
    folder = c.folder("special", "mesh_symlink_loop")
    os.symlink("m.obj", folder / "m.obj")
    _mesh_runs(c, "special", "mesh_symlink_loop", folder, "m.obj")
    obj, mtl = base["obj"], base["mtl"]
    for name, make in {
        "texture_fifo": lambda d: os.mkfifo(d / "skin.png"),
        "texture_is_folder": lambda d: (d / "skin.png").mkdir(),
        "mtl_fifo": lambda d: os.mkfifo(d / "skin.mtl"),
        "mtl_is_folder": lambda d: (d / "skin.mtl").mkdir(),
    }.items():
        files = {"sphere.obj": obj, "skin.mtl": mtl, "skin.png": base["png"]}
        files.pop("skin.png" if "texture" in name else "skin.mtl")
        folder = c.files("special", name, files)
        make(folder)
        _mesh_runs(c, "special", name, folder, "sphere.obj")
    for name, link in {"texture_symlink_loop": "skin.png", "mtl_symlink_loop": "skin.mtl"}.items():
        files = {"sphere.obj": obj, "skin.mtl": mtl, "skin.png": base["png"]}
        files.pop(link)
        folder = c.files("special", name, files)
        os.symlink(link, folder / link)  # a link to itself: resolving it loops
        _mesh_runs(c, "special", name, folder, "sphere.obj")
    folder = c.files("special", "empty_message", {"m.glb": base["glb"]})
    for case, text in {"empty_message": "", "blank_message": "  "}.items():
        c.run("special", case, "bad argument", "embed",
              ["embed", folder / "m.glb", "-o", "{out}/marked.glb", "--message", text, "--views", 1], "error", folder)
    gltf = dict(base["gltf"])
    model = gltf.pop("model.gltf")
    bin_name = json.loads(model)["buffers"][0]["uri"]
    folder = c.files("special", "gltf_buffer_fifo", {"m.gltf": model, **{k: v for k, v in gltf.items() if k != bin_name}})
    os.mkfifo(folder / bin_name)
    _mesh_runs(c, "special", "gltf_buffer_fifo", folder, "m.gltf")
    edited = json.loads(model)
    edited["images"] = [{"uri": "pipe.png"}]
    edited["textures"] = [{"source": 0}]
    folder = c.files("special", "gltf_image_fifo", {"m.gltf": json.dumps(edited), **gltf})
    os.mkfifo(folder / "pipe.png")
    _mesh_runs(c, "special", "gltf_image_fifo", folder, "m.gltf")


def _mesh_runs(c: Corpus, group: str, case: str, folder: Path, main: str) -> None:
    suffix = Path(main).suffix
    path = folder / main
    c.run(group, case, "special file", "info", ["info", path], "error", folder)
    c.run(group, case, "special file", "render", ["render", path, "-o", "{out}/view.png", "--width", 32, "--height", 32],
          "error", folder)
    c.run(group, case, "special file", "embed", ["embed", path, "-o", f"{{out}}/marked{suffix}", "--bits", MESSAGE],
          "error", folder)


# ---------------------------------------------------------------- pictures and outputs


def _with_camera(image: Image.Image, camera: str, **options) -> bytes:
    info = PngImagePlugin.PngInfo()
    info.add_text(CAMERA_KEY, camera)
    return _png(image, pnginfo=info, **options)


def _picture_cases(c: Corpus, base: dict) -> None:
    from meshseal.cli import main

    folder = c.files("pictures", "_mesh", {"m.glb": base["glb"]})
    mesh = folder / "m.glb"
    render = c.reference = c.root / "_render" / "view.png"
    with contextlib.redirect_stdout(io.StringIO()):  # render prints the paths it writes
        assert main(["render", str(mesh), "-o", str(render), "--width", "96", "--height", "96"]) == 0
    source = Image.open(render)
    source.load()
    camera = source.info[CAMERA_KEY]
    rgb = source.convert("RGB")
    grey16 = Image.fromarray((np.asarray(rgb.convert("L")).astype(np.uint16) * 257))
    rgba = rgb.convert("RGBA")
    rgba.putalpha(Image.fromarray(((np.asarray(rgb).max(-1) > 0) * 255).astype(np.uint8)))
    transparent = rgb.convert("RGBA")
    transparent.putalpha(0)
    palette = rgb.convert("P", palette=Image.Palette.ADAPTIVE, colors=256)
    jpeg = _encode(rgb, "JPEG", quality=95)
    gif = _encode(palette, "GIF", save_all=True, append_images=[palette.rotate(20)])
    valid = {  # each carries the camera, so detection needs no registration (quick)
        "valid_rgb": _with_camera(rgb, camera), "valid_grey": _with_camera(rgb.convert("L"), camera),
        "valid_palette": _with_camera(palette, camera), "valid_grey_alpha": _with_camera(rgb.convert("LA"), camera),
        "valid_grey16": _with_camera(grey16, camera), "valid_rgba_cutout": _with_camera(rgba, camera),
        "valid_bilevel": _with_camera(rgb.convert("L").point(lambda v: 255 if v > 8 else 0).convert("1"), camera),
    }
    hostile = {
        "bomb_png": _bomb_png(), "bomb_png_tall": _bomb_png(20, 200_000_000),
        "one_pixel": _with_camera(rgb.resize((1, 1)), camera), "fifteen_pixels": _with_camera(rgb.resize((15, 15)), camera),
        "one_row": _with_camera(rgb.resize((96, 1)), camera),
        "fully_transparent": _with_camera(transparent, camera),
        "fully_transparent_palette": _with_camera(Image.new("P", (64, 64), 0), camera, transparency=0),
        "plain_colour": _with_camera(Image.new("RGB", (64, 64), (40, 90, 200)), camera),
        "plain_grey16": _with_camera(Image.new("I;16", (64, 64), 30000), camera),
        "plain_black_jpeg": _encode(Image.new("RGB", (64, 64)), "JPEG"),
        "empty_file": b"", "text_file": "this is not a picture\n", "mesh_as_picture": base["glb"][:4000],
        "png_bad_crc": _with_camera(rgb, camera)[:30] + b"\xff\xff" + _with_camera(rgb, camera)[32:],
        "png_header_only": _with_camera(rgb, camera)[:33], "png_signature_only": b"\x89PNG\r\n\x1a\n",
        "camera_not_json": _with_camera(rgb, "{not json"), "camera_missing_fields": _with_camera(rgb, '{"eye": [0, 0, 1]}'),
        "camera_nan": _with_camera(rgb, camera.replace("[", "[NaN, ", 1)),
        "camera_fov_zero": _with_camera(rgb, json.dumps(json.loads(camera) | {"fov_y": 0})),
        "tiff_truncated": _encode(rgb, "TIFF")[:3000], "bmp_truncated": _encode(rgb, "BMP")[:5000],
        "webp_truncated": _encode(rgb, "WEBP")[:200], "gif_truncated": gif[:300],
        "jpeg_cut_header": jpeg[:100], "float_tiff_nan": _encode(Image.fromarray(np.full((32, 32), np.nan, np.float32)), "TIFF"),
    }
    png = _with_camera(rgb, camera)
    for k, cut in enumerate(_cuts(png, 40, 5)):
        hostile[f"png_cut_{k}"] = png[:cut]
    for k, cut in enumerate(_cuts(jpeg, 200, 3)):
        hostile[f"jpeg_cut_{k}"] = jpeg[:cut]
    for name, data in valid.items():
        case = c.files("pictures", name, {"picture.png": data})
        c.run("pictures", name, "control", "detect", ["detect", case / "picture.png", "--mesh", mesh], "ok", case,
              hostile=False)
    for name, data in hostile.items():
        case = c.files("pictures", name, {"picture.png": data})
        c.run("pictures", name, "broken picture", "detect", ["detect", case / "picture.png", "--mesh", mesh], "error", case)
    for name, make in {"picture_fifo": lambda d: os.mkfifo(d / "picture.png"),
                       "picture_device": lambda d: os.symlink("/dev/zero", d / "picture.png"),
                       "picture_is_folder": lambda d: (d / "picture.png").mkdir(),
                       "picture_missing": lambda d: None}.items():
        case = c.folder("pictures", name)
        make(case)
        c.run("pictures", name, "special file", "detect", ["detect", case / "picture.png", "--mesh", mesh], "error", case)
    # Several pictures in one call, the broken one in the middle: the good ones are still read.
    case = c.files("pictures", "mixed_call", {"a.png": valid["valid_rgb"], "b.png": _bomb_png(), "c.png": valid["valid_grey"]})
    c.run("pictures", "mixed_call", "control", "detect", ["detect", case / "a.png", case / "b.png", case / "c.png", "--mesh",
                                                          mesh], "any", case, hostile=False)
    # The same pictures in the odd formats that need registration are checked in test_corpus.py
    # through the picture loader (the conversions), not here (registration is not quick).
    c.odd_pictures = {"rgb": png, "cmyk_jpeg": _encode(rgb.convert("CMYK"), "JPEG", quality=95),
                      "progressive_jpeg": _encode(rgb, "JPEG", quality=95, progressive=True), "animated_gif": gif,
                      "palette_transparency": _png(palette, transparency=palette.getpixel((0, 0))), "tiff": _encode(rgb, "TIFF"),
                      "rgb16_tiff": _encode(grey16, "TIFF"), "webp": _encode(rgb, "WEBP", lossless=True),
                      "bmp": _encode(rgb, "BMP")}


def _output_cases(c: Corpus, base: dict) -> None:
    """Where outputs go: a missing folder is created; an input (also through a link), a folder, a
    special file or a path under a file is refused before any work; nothing partial is left."""
    glb = base["glb"]
    render = lambda path, out: ["render", path, "-o", out, "--width", 32, "--height", 32]  # noqa: E731
    embed = lambda path, out: ["embed", path, "-o", out, "--bits", MESSAGE, "--views", 1]  # noqa: E731
    case = c.files("outputs", "missing_folder", {"m.glb": glb})
    c.run("outputs", "missing_folder", "output path", "render", render(case / "m.glb", "{out}/new/deeper/view.png"), "ok",
          case, ("new/deeper/view.png",), hostile=False)
    c.run("outputs", "missing_folder", "output path", "embed", embed(case / "m.glb", "{out}/new/marked.glb"), "ok",
          case, ("new/marked.glb",), hostile=False)
    refusals = {  # embed -o TARGET
        "same_path": lambda d: d / "m.glb",
        "hard_link": lambda d: os.link(d / "m.glb", d / "link.glb") or d / "link.glb",
        "symbolic_link": lambda d: os.symlink("m.glb", d / "link.glb") or d / "link.glb",
        "dot_dot_path": lambda d: d / "sub" / ".." / "m.glb",
        "existing_folder": lambda d: (d / "out.glb").mkdir() or d / "out.glb",
        "existing_fifo": lambda d: os.mkfifo(d / "out.glb") or d / "out.glb",
        "under_a_file": lambda d: d / "m.glb" / "out.glb",
    }
    for name, make in refusals.items():
        case = c.files("outputs", name, {"m.glb": glb, "sub/keep": ""})
        c.run("outputs", name, "output path", "embed", embed(case / "m.glb", make(case)), "error", case)
    obj = {"sphere.obj": base["obj"], "skin.mtl": base["mtl"], "skin.png": base["png"]}
    refusals = {  # render -o TARGET.png, the OBJ's texture being an input
        "render_texture_path": lambda d: d / "skin.png",
        "render_texture_hard_link": lambda d: os.link(d / "skin.png", d / "shot.png") or d / "shot.png",
        "render_texture_symbolic_link": lambda d: os.symlink("skin.png", d / "shot.png") or d / "shot.png",
        "render_existing_folder": lambda d: (d / "shot.png").mkdir() or d / "shot.png",
        "render_existing_fifo": lambda d: os.mkfifo(d / "shot.png") or d / "shot.png",
        "render_under_a_file": lambda d: d / "skin.mtl" / "shot.png",
    }
    for name, make in refusals.items():
        case = c.files("outputs", name, obj)
        c.run("outputs", name, "output path", "render", render(case / "sphere.obj", make(case)), "error", case)
    case = c.files("outputs", "preview_hard_link_to_texture", obj)
    os.link(case / "skin.png", case / "shot.png")
    c.run("outputs", "preview_hard_link_to_texture", "output path", "embed",
          ["embed", case / "sphere.obj", "-o", "{out}/marked.obj", "--bits", MESSAGE, "--views", 1, "--preview",
           case / "shot.png"], "error", case)
    case = c.files("outputs", "preview_is_output", {"m.glb": glb})
    c.run("outputs", "preview_is_output", "output path", "embed",
          ["embed", case / "m.glb", "-o", "{out}/x.glb", "--bits", MESSAGE, "--preview", "{out}/x.glb"], "error", case)
    if hasattr(os, "geteuid") and os.geteuid() != 0:  # root writes into read-only folders anyway
        case = c.files("outputs", "read_only_folder", {"m.glb": glb})
        locked = c.root / "_locked"
        locked.mkdir()
        locked.chmod(0o555)
        c.run("outputs", "read_only_folder", "output path", "render", render(case / "m.glb", locked / "view.png"), "error", case)
        c.run("outputs", "read_only_folder", "output path", "embed", embed(case / "m.glb", locked / "m.glb"), "error", case)


GROUPS = ("obj", "ply", "off", "stl", "gltf", "special", "pictures", "outputs")


def build(root: Path) -> Corpus:
    """Write the corpus under `root` (which must not exist yet); returns it with its runs."""
    root = Path(root)
    root.mkdir(parents=True)
    corpus = Corpus(root)
    base = _bases()
    for make in (_obj_cases, _ply_cases, _off_cases, _stl_cases, _gltf_cases, _special_cases, _picture_cases,
                 _output_cases):
        make(corpus, base)
    return corpus


def counts(corpus: Corpus) -> dict[str, int]:
    """Cases per class (a case is one input, tried with every command that reads it)."""
    result: dict[str, int] = {}
    for cls, _ in corpus.cases.values():
        result[cls] = result.get(cls, 0) + 1
    return dict(sorted(result.items()))


if __name__ == "__main__":
    built = build(Path(sys.argv[1]))
    for cls, number in counts(built).items():
        print(f"{number:4d}  {cls}")
    print(f"{sum(1 for _, hostile in built.cases.values() if hostile):4d}  hostile inputs, "
          f"{len(built.runs)} runs")
