"""Mesh loading, saving and preprocessing on the real fixtures and on broken files."""

from __future__ import annotations

import os
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from meshseal.errors import MeshError
from meshseal.mesh import (Material, Mesh, load, normalize, save, simplify, spherical_uv, to_z_up,
                           vertex_normals)
from meshseal.mesh import files as mesh_files

FIXTURES = Path(__file__).parent / "fixtures"

# path: (vertices, faces, up axis, [(material name, texture size or None)], has uvs)
EXPECTED = {
    "bunny.glb": (2044, 3998, "y", [("bunny_grass", (256, 256))], True),
    "suzanne.glb": (2106, 3998, "y", [("suzanne_gravel", (256, 256))], True),
    "multi_material.glb": (639, 1152, "y", [("fabric", (256, 256)), ("frame", (200, 200)), ("metal", None)], True),
    "bunny.ply": (1001, 1998, "z", [("bunny.ply", None)], False),
    "cube.off": (8, 12, "z", [("cube.off", None)], False),
    "tetra.stl": (12, 4, "z", [("tetra.stl", None)], False),
    "teapot/teapot.obj": (1405, 2256, "y", [("teapot", (256, 256))], True),
    "sh3d_crate/crate.obj": (1728, 864, "y", [("Crate", (256, 256))], True),
    "sh3d_deckChair/deckChair.obj": (849, 1152, "y", [("ChairFrame", (200, 200)), ("Chair_Fabric", (256, 256)),
                                                      ("Metal", None)], True),
}


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}


def _no_temp_files(folder: Path) -> bool:
    return not [p for p in folder.rglob("*") if p.name.endswith(".tmp")]


# ---------------------------------------------------------------- loading


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_load_fixture(name):
    n_vertices, n_faces, up_axis, materials, has_uvs = EXPECTED[name]
    mesh = load(FIXTURES / name)
    assert (mesh.n_vertices, mesh.n_faces, mesh.up_axis) == (n_vertices, n_faces, up_axis)
    assert [m.name for m in mesh.materials] == [m[0] for m in materials]
    for material, (_, size) in zip(mesh.materials, materials):
        if size is None:
            assert material.texture is None
        else:
            assert tuple(material.texture.shape) == (*size, 3)
            assert material.texture.dtype == torch.float32
            assert 0.0 <= float(material.texture.min()) and float(material.texture.max()) <= 1.0
    assert (mesh.uvs is not None) == has_uvs
    if has_uvs:
        assert mesh.uvs.shape == (n_vertices, 2) and torch.isfinite(mesh.uvs).all()
    assert mesh.positions.shape == mesh.normals.shape == (n_vertices, 3)
    assert mesh.faces.dtype == torch.int64 and int(mesh.faces.max()) < n_vertices
    assert torch.isfinite(mesh.positions).all()
    assert torch.allclose(mesh.normals.norm(dim=-1), torch.ones(n_vertices), atol=1e-4)
    # Every material is used by some face, and face_material indexes the table.
    assert sorted(torch.unique(mesh.face_material).tolist()) == list(range(len(materials)))


def test_multi_material_parts_and_nodes():
    mesh = load(FIXTURES / "multi_material.glb")
    parts = mesh.source.parts
    assert [p.node for p in parts] == ["fabric", "frame", "metal"]
    # The root node scales by 0.01: positions are in world units (the OBJ's scale * 0.01).
    obj = load(FIXTURES / "sh3d_deckChair" / "deckChair.obj")
    extent = lambda m: (m.positions.max(0).values - m.positions.min(0).values)  # noqa: E731
    assert torch.allclose(extent(mesh) * 100.0, extent(obj), rtol=1e-3)


def test_double_sided_sheet_has_unit_normals():
    # The deck chair's fabric in the GLB is a double-sided sheet sharing vertices: the face normals
    # cancel, yet every vertex needs a proper normal for shading.
    mesh = load(FIXTURES / "multi_material.glb")
    fabric = mesh.face_material == [m.name for m in mesh.materials].index("fabric")
    vertices = mesh.faces[fabric].unique()
    normals = mesh.normals[vertices]
    assert torch.allclose(normals.norm(dim=-1), torch.ones(len(vertices)), atol=1e-4)


def test_up_axis_override():
    assert load(FIXTURES / "bunny.glb", up_axis="z").up_axis == "z"
    assert load(FIXTURES / "cube.off", up_axis="y").up_axis == "y"


def test_missing_texture_is_a_warning(tmp_path, capsys):
    folder = tmp_path / "teapot"
    shutil.copytree(FIXTURES / "teapot", folder)
    (folder / "teapot.jpg").unlink()
    mesh = load(folder / "teapot.obj")
    assert mesh.n_faces == 2256 and mesh.materials[0].texture is None
    assert mesh.uvs is not None
    err = capsys.readouterr().err
    assert "warning" in err and "teapot.jpg" in err and len(err.strip().splitlines()) == 1


def test_missing_mtl_is_a_warning(tmp_path, capsys):
    folder = tmp_path / "crate"
    shutil.copytree(FIXTURES / "sh3d_crate", folder)
    (folder / "crate.mtl").unlink()
    mesh = load(folder / "crate.obj")
    assert mesh.n_faces == 864 and all(m.texture is None for m in mesh.materials)
    assert "crate.mtl" in capsys.readouterr().err


# ---------------------------------------------------------------- bad input


def _write(path: Path, data: bytes | str) -> Path:
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    return path


TRIANGLE = "v 0 0 0\nv 1 0 0\nv 0 1 0\n"

BAD_INPUTS = {
    "truncated_glb": lambda d: _write(d / "bunny.glb", (FIXTURES / "bunny.glb").read_bytes()[:100_000]),
    "glb_header_only": lambda d: _write(d / "head.glb", (FIXTURES / "bunny.glb").read_bytes()[:12]),
    "binary_garbage_obj": lambda d: _write(d / "garbage.obj", np.random.default_rng(0).bytes(4096)),
    "text_garbage_obj": lambda d: _write(d / "text.obj", "hello world\nthis is not\nf a b c\n"),
    "empty_obj": lambda d: _write(d / "empty.obj", b""),
    "empty_glb": lambda d: _write(d / "empty.glb", b""),
    "nan_vertices": lambda d: _write(d / "nan.obj", "v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n"),
    "inf_vertices_off": lambda d: _write(d / "inf.off", "OFF\n3 1 0\n0 0 0\n1 0 0\ninf 1 0\n3 0 1 2\n"),
    "face_index_out_of_range": lambda d: _write(d / "range.obj", TRIANGLE + "f 1 2 9\n"),
    "off_index_out_of_range": lambda d: _write(d / "range.off", "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n"),
    "no_faces": lambda d: _write(d / "points.obj", TRIANGLE),
    "png_renamed_obj": lambda d: _write(d / "image.obj", (FIXTURES / "textures" / "brick.png").read_bytes()),
    "png_renamed_glb": lambda d: _write(d / "image.glb", (FIXTURES / "textures" / "brick.png").read_bytes()),
    "png_renamed_stl": lambda d: _write(d / "image.stl", (FIXTURES / "textures" / "brick.png").read_bytes()),
    "unsupported_extension": lambda d: _write(d / "mesh.fbx", TRIANGLE + "f 1 2 3\n"),
    "no_extension": lambda d: _write(d / "mesh", TRIANGLE + "f 1 2 3\n"),
    "missing_file": lambda d: d / "nothing_here.obj",
    "directory": lambda d: (d / "folder.obj").mkdir() or d / "folder.obj",
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input_is_one_line_mesh_error(case, tmp_path):
    path = BAD_INPUTS[case](tmp_path)
    with pytest.raises(MeshError) as info:
        load(path)
    message = str(info.value)
    assert message and "\n" not in message
    assert str(path.name) in message


CUBE_OFF = (FIXTURES / "cube.off").read_text()
ASCII_PLY = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
             "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")

# Issue #14: files trimesh used to read silently, mangled. case -> (file, what the one-line error says)
SILENTLY_MANGLED = {
    "obj_index_zero": ("z.obj", TRIANGLE + "f 0 1 2\n", "index 0 (OBJ indices start at 1)"),
    "obj_vt_past_end": ("t.obj", TRIANGLE + "vt 0 0\nf 1/1 2/1 3/2\n", "vt index 2, but the file has only 1"),
    "obj_vn_past_end": ("n.obj", TRIANGLE + "vn 0 0 1\nf 1//1 2//1 3//4\n", "vn index 4"),
    "off_cut_in_face": ("cut.off", CUBE_OFF.rstrip()[:-2], "line 17: a face needs"),
    "off_counts_promise_more": ("more.off", CUBE_OFF.replace("8 6 0", "8 7 0"), "promises 8 vertices and 7 faces"),
    "ply_cut_in_face": ("cut.ply", ASCII_PLY[:-3], "a 'face' record has 3 values, its properties need 4"),
    "ply_counts_promise_more": ("more.ply", ASCII_PLY.replace("face 1", "face 2"), "promises 2 'face' records"),
    "ply_format_no_format": ("fmt.ply", ASCII_PLY.replace("ascii 1.0", "banana 1.0"), "names no PLY format"),
}


@pytest.mark.parametrize("case", sorted(SILENTLY_MANGLED))
def test_mangled_structure_is_a_one_line_error(case, tmp_path):
    name, text, expected = SILENTLY_MANGLED[case]
    with pytest.raises(MeshError) as info:
        load(_write(tmp_path / name, text))
    assert str(info.value).startswith(f"{tmp_path / name}: ") and expected in str(info.value)


def test_glb_overwritten_json_and_negative_count(tmp_path):
    import json
    import struct

    data = (FIXTURES / "bunny.glb").read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    broken = bytearray(data)
    broken[60:63] = b"\x00#\x00"
    with pytest.raises(MeshError, match="JSON chunk is not valid JSON"):
        load(_write(tmp_path / "json.glb", bytes(broken)))
    document = json.loads(data[20:20 + length])
    document["accessors"][1]["count"] = -4
    body = json.dumps(document).encode()
    body += b" " * (-len(body) % 4)
    rest = data[20 + length:]
    glb = b"glTF" + struct.pack("<II", 2, 20 + len(body) + len(rest)) + struct.pack("<I4s", len(body), b"JSON") + body + rest
    with pytest.raises(MeshError, match="accessor 1 count is -4"):
        load(_write(tmp_path / "count.glb", glb))


def test_texture_named_by_a_pipe_is_refused_at_once(tmp_path):
    folder = tmp_path / "teapot"
    shutil.copytree(FIXTURES / "teapot", folder)
    (folder / "teapot.jpg").unlink()
    os.mkfifo(folder / "teapot.jpg")  # reading it would block forever
    with pytest.raises(MeshError, match="is a named pipe, not a regular texture file"):
        load(folder / "teapot.obj")


# ---------------------------------------------------------------- saving


def test_obj_round_trip(tmp_path):
    mesh = load(FIXTURES / "teapot" / "teapot.obj")
    mesh.materials[0].texture = 1.0 - mesh.materials[0].texture  # a visible change
    written = save(mesh, tmp_path / "out.obj")
    assert {p.name for p in written} >= {"out.obj", "out.mtl"}
    assert _no_temp_files(tmp_path)
    again = load(tmp_path / "out.obj")
    assert [m.name for m in again.materials] == ["teapot"]
    assert _psnr(again.materials[0].texture, mesh.materials[0].texture) > 45  # teapot.jpg: JPEG at quality 95
    assert again.n_faces == mesh.n_faces and again.n_vertices == mesh.n_vertices
    assert torch.allclose(again.positions, mesh.positions, atol=1e-5)
    assert torch.allclose(again.uvs, mesh.uvs, atol=1e-5)
    assert (again.normals * mesh.normals).sum(-1).min() > 0.999


def test_obj_round_trip_keeps_changed_geometry(tmp_path):
    mesh = load(FIXTURES / "sh3d_crate" / "crate.obj")
    mesh.positions = mesh.positions * 2.0
    mesh.uvs = mesh.uvs * 0.5
    save(mesh, tmp_path / "crate2.obj")
    again = load(tmp_path / "crate2.obj")
    assert torch.allclose(again.positions, mesh.positions, atol=1e-4)
    assert torch.allclose(again.uvs, mesh.uvs, atol=1e-5)


def test_glb_round_trip(tmp_path):
    mesh = load(FIXTURES / "bunny.glb")
    texture = mesh.materials[0].texture.clone()
    texture[:64, :64] = torch.tensor([1.0, 0.0, 0.0])  # a red patch in the top-left
    mesh.materials[0].texture = texture
    save(mesh, tmp_path / "bunny_marked.glb")
    assert _no_temp_files(tmp_path)
    again = load(tmp_path / "bunny_marked.glb")
    assert [m.name for m in again.materials] == ["bunny_grass"]
    assert [p.node for p in again.source.parts] == ["bunny"]
    assert torch.allclose(again.materials[0].texture, texture, atol=1.0 / 255 + 1e-6)
    assert again.n_faces == mesh.n_faces and again.n_vertices == mesh.n_vertices
    assert torch.allclose(again.positions, mesh.positions, atol=1e-5)
    assert torch.allclose(again.uvs, mesh.uvs, atol=1e-5)
    assert (again.normals * mesh.normals).sum(-1).min() > 0.999


def test_glb_multi_material_save_keeps_textures_names_and_nodes(tmp_path):
    mesh = load(FIXTURES / "multi_material.glb")
    changed = {}
    for material in mesh.materials:
        if material.texture is not None:
            material.texture = material.texture.flip(-1)  # swap R and B
            changed[material.name] = material.texture
    assert len(changed) >= 2
    save(mesh, tmp_path / "chair.glb")
    again = load(tmp_path / "chair.glb")
    assert [m.name for m in again.materials] == [m.name for m in mesh.materials]
    assert [p.node for p in again.source.parts] == [p.node for p in mesh.source.parts]
    assert "deck_chair" in again.source.scene.graph.nodes  # the root node survives
    for material in again.materials:
        if material.name in changed:
            assert torch.allclose(material.texture, changed[material.name], atol=1.0 / 255 + 1e-6)
    assert torch.allclose(again.positions, mesh.positions, atol=1e-5)
    assert torch.equal(again.face_material, mesh.face_material)


def test_obj_multi_material_save_keeps_textures(tmp_path):
    mesh = load(FIXTURES / "sh3d_deckChair" / "deckChair.obj")
    save(mesh, tmp_path / "chair.obj")
    images = [p for p in tmp_path.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg")]
    assert len(images) >= 2
    again = load(tmp_path / "chair.obj")
    assert [m.name for m in again.materials] == ["ChairFrame", "Chair_Fabric", "Metal"]
    assert sum(m.texture is not None for m in again.materials) == 2
    for before, after in zip(mesh.materials, again.materials):
        if before.texture is not None:
            assert _psnr(before.texture, after.texture) > 45  # JPEG in, JPEG out at quality 95


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(10 * torch.log10(1.0 / ((a - b) ** 2).mean()))


def test_obj_round_trip_keeps_object_names_material_fields_and_texture_names(tmp_path):
    """deckChair.obj: one object 'Chair.002_Group1.002' with three materials, an MTL with Ni, d, illum,
    JPEG textures. The output keeps the object, every MTL field, the textures' names with the output's
    suffix and their format (JPEG, 4:4:4 chroma); a PNG texture stays PNG."""
    from PIL import Image

    folder = FIXTURES / "sh3d_deckChair"
    mesh = load(folder / "deckChair.obj")
    written = save(mesh, tmp_path / "deckChair_marked.obj")
    assert sorted(p.name for p in written) == ["BEuropean_Beech_marked.jpg", "BlueWhite_Stripes_marked.jpg",
                                               "deckChair_marked.mtl", "deckChair_marked.obj"]
    obj = (tmp_path / "deckChair_marked.obj").read_text()
    assert [line for line in obj.splitlines() if line.startswith(("o ", "g "))] == ["o Chair.002_Group1.002"]
    assert [line for line in obj.splitlines() if line.startswith("usemtl")] == \
        ["usemtl Metal", "usemtl ChairFrame", "usemtl Chair_Fabric"]
    source = (folder / "deckChair.mtl").read_text().splitlines()
    expected = [line.replace("Beech.jpg", "Beech_marked.jpg").replace("Stripes.jpg", "Stripes_marked.jpg")
                for line in source if line.strip() and not line.startswith("#")]
    assert [line for line in (tmp_path / "deckChair_marked.mtl").read_text().splitlines()
            if line.strip() and not line.startswith("#")] == expected
    with Image.open(tmp_path / "BEuropean_Beech_marked.jpg") as image:
        assert image.format == "JPEG" and image.layer[0][1:3] == image.layer[1][1:3] == (1, 1)  # 4:4:4
    again = load(tmp_path / "deckChair_marked.obj")
    assert [p.node for p in again.source.parts] == [p.node for p in mesh.source.parts]
    assert torch.equal(again.face_material, mesh.face_material)
    # Another output name: the suffix is '_' and that name. A PNG texture stays PNG; other maps are copied.
    written = save(mesh, tmp_path / "other" / "chair.obj")
    assert "BEuropean_Beech_chair.jpg" in {p.name for p in written}
    sphere = tmp_path / "box"
    sphere.mkdir()
    import trimesh
    from PIL import Image as PILImage

    textured = trimesh.creation.box()
    textured.visual = trimesh.visual.TextureVisuals(uv=np.random.default_rng(0).random((8, 2)),
                                                    image=PILImage.new("RGB", (8, 8), (200, 20, 20)))
    (sphere / "box.obj").write_text("mtllib box.mtl\ng Box\nusemtl skin\n"
                                    + "".join(f"v {x} {y} {z}\n" for x, y, z in textured.vertices)
                                    + "".join(f"vt {u} {v}\n" for u, v in textured.visual.uv)
                                    + "".join(f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}\n"
                                              for a, b, c in textured.faces))
    (sphere / "box.mtl").write_text("newmtl skin\nKd 1 1 1\nillum 1\nmap_Kd skin.png\nmap_Bump bump.png\n")
    PILImage.new("RGB", (8, 8), (200, 20, 20)).save(sphere / "skin.png")
    PILImage.new("RGB", (8, 8), (128, 128, 255)).save(sphere / "bump.png")
    written = save(load(sphere / "box.obj"), tmp_path / "out" / "box_marked.obj")
    assert sorted(p.name for p in written) == ["box_marked.mtl", "box_marked.obj", "bump.png", "skin_marked.png"]
    assert (tmp_path / "out" / "box_marked.mtl").read_text().split("\n")[2:] == \
        ["newmtl skin", "Kd 1 1 1", "illum 1", "map_Kd skin_marked.png", "map_Bump bump.png", ""]
    assert [line for line in (tmp_path / "out" / "box_marked.obj").read_text().splitlines()
            if line.startswith(("o ", "g "))] == ["g Box"]
    with PILImage.open(tmp_path / "out" / "skin_marked.png") as image:
        assert image.format == "PNG"


def test_save_in_memory_mesh(tmp_path):
    positions = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    faces = torch.tensor([[0, 1, 2]])
    mesh = Mesh(positions, vertex_normals(positions, faces), faces,
                uvs=torch.tensor([[0.0, 0], [1, 0], [0, 1]]),
                materials=[Material(name="m", texture=torch.rand(8, 8, 3))])
    save(mesh, tmp_path / "tri.obj")
    again = load(tmp_path / "tri.obj")
    assert again.n_faces == 1 and again.materials[0].texture is not None
    save(mesh, tmp_path / "tri.glb")
    assert load(tmp_path / "tri.glb").n_faces == 1


def test_save_format_must_match(tmp_path):
    mesh = load(FIXTURES / "bunny.glb")
    with pytest.raises(MeshError, match="format"):
        save(mesh, tmp_path / "bunny.obj")
    with pytest.raises(MeshError, match="unsupported"):
        save(mesh, tmp_path / "bunny.fbx")


def test_save_never_overwrites_the_input(tmp_path):
    folder = tmp_path / "teapot"
    shutil.copytree(FIXTURES / "teapot", folder)
    before = _files(folder)
    mesh = load(folder / "teapot.obj")
    with pytest.raises(MeshError, match="overwrite"):
        save(mesh, folder / "teapot.obj")
    glb = tmp_path / "bunny.glb"
    shutil.copy(FIXTURES / "bunny.glb", glb)
    with pytest.raises(MeshError, match="overwrite"):
        save(load(glb), glb)
    assert _files(folder) == before and glb.read_bytes() == (FIXTURES / "bunny.glb").read_bytes()
    assert _no_temp_files(tmp_path)


def test_save_never_overwrites_an_input_texture(tmp_path):
    # Another map of the OBJ's material has exactly the name the output's texture would get.
    folder = tmp_path / "teapot"
    shutil.copytree(FIXTURES / "teapot", folder)
    mesh = load(folder / "teapot.obj")
    probe = save(mesh, tmp_path / "probe" / "out.obj")
    texture_name = next(p.name for p in probe if p.suffix.lower() in (".png", ".jpg"))
    shutil.copy(folder / "teapot.jpg", folder / texture_name)
    mtl = folder / "teapot.mtl"
    mtl.write_text(mtl.read_text() + f"\nmap_Bump {texture_name}\n")
    before = _files(folder)
    mesh = load(folder / "teapot.obj")
    assert mesh.materials[0].texture is not None
    with pytest.raises(MeshError, match="overwrite"):
        save(mesh, folder / "out.obj")
    assert _files(folder) == before  # nothing written, not even the .obj
    assert _no_temp_files(folder)


def test_save_is_atomic(tmp_path, monkeypatch):
    target = tmp_path / "bunny_out.glb"
    target.write_bytes(b"previous content")
    mesh = load(FIXTURES / "bunny.glb")

    def failing_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(mesh_files.os, "replace", failing_replace)
    with pytest.raises(MeshError, match="disk full"):
        save(mesh, target)
    assert target.read_bytes() == b"previous content"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bunny_out.glb"]


# ---------------------------------------------------------------- preprocessing


def test_normalize_bounds_and_aspect():
    mesh = load(FIXTURES / "sh3d_crate" / "crate.obj")
    extent = mesh.positions.max(0).values - mesh.positions.min(0).values
    out = normalize(mesh)
    low, high = out.positions.min(0).values, out.positions.max(0).values
    assert float(low.min()) >= -1.0 - 1e-5 and float(high.max()) <= 1.0 + 1e-5
    assert torch.allclose((high - low).max(), torch.tensor(2.0), atol=1e-5)
    assert torch.allclose(low + high, torch.zeros(3), atol=1e-5)  # centred
    new_extent = high - low
    assert torch.allclose(new_extent / new_extent.max(), extent / extent.max(), atol=1e-5)
    assert torch.equal(out.faces, mesh.faces) and out.materials is mesh.materials


def test_to_z_up():
    mesh = load(FIXTURES / "teapot" / "teapot.obj")  # Y-up: the lid is at max y
    lid = int(mesh.positions[:, 1].argmax())
    out = to_z_up(mesh)
    assert out.up_axis == "z"
    x, y, z = mesh.positions.unbind(-1)
    assert torch.allclose(out.positions, torch.stack([x, -z, y], dim=-1))
    assert int(out.positions[:, 2].argmax()) == lid
    nx, ny, nz = mesh.normals.unbind(-1)
    assert torch.allclose(out.normals, torch.stack([nx, -nz, ny], dim=-1))
    z_up = load(FIXTURES / "cube.off")
    assert to_z_up(z_up) is z_up
    # A proper rotation: handedness (and so the winding of faces seen from outside) is kept.
    rotation = torch.stack([to_z_up(replace_positions(mesh, torch.eye(3)[k])).positions[0] for k in range(3)])
    assert torch.allclose(torch.linalg.det(rotation), torch.tensor(1.0))


def replace_positions(mesh: Mesh, point: torch.Tensor) -> Mesh:
    copy = mesh.copy()
    copy.positions = point.reshape(1, 3).expand(mesh.n_vertices, 3).clone()
    return copy


def test_simplify_keeps_uvs_and_materials():
    mesh = load(FIXTURES / "sh3d_deckChair" / "deckChair.obj")
    out = simplify(mesh, 600)
    assert 400 <= out.n_faces <= 700
    assert out.uvs is not None and out.uvs.shape == (out.n_vertices, 2)
    assert out.normals.shape == (out.n_vertices, 3)
    assert out.face_material.shape == (out.n_faces,)
    assert set(out.face_material.tolist()) == {0, 1, 2}
    assert len(out.materials) == 3 and sum(m.texture is not None for m in out.materials) == 2
    assert int(out.faces.max()) < out.n_vertices
    assert out.uvs.min() >= mesh.uvs.min() - 1e-6 and out.uvs.max() <= mesh.uvs.max() + 1e-6


def test_simplify_keeps_the_texture_on_the_surface():
    """A bumpy sheet textured by its own x, y: decimated, each vertex's UV must still be its x, y (the
    texture stays where it was as vertices move), not the UV of a vertex that collapsed into it."""
    n = 41
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    z = 0.08 * np.sin(6 * x) * np.cos(5 * y)
    positions = torch.tensor(np.stack([x.ravel(), y.ravel(), z.ravel()], 1), dtype=torch.float32)
    grid = np.arange(n * n).reshape(n, n)
    a, b, c, d = grid[:-1, :-1].ravel(), grid[:-1, 1:].ravel(), grid[1:, :-1].ravel(), grid[1:, 1:].ravel()
    faces = torch.tensor(np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]))
    mesh = Mesh(positions, vertex_normals(positions, faces), faces, positions[:, :2].clone())
    out = simplify(mesh, mesh.n_faces // 4)
    assert out.n_faces <= mesh.n_faces // 4
    moved = (out.uvs - out.positions[:, :2]).norm(dim=1)  # a vertex's UV as its position: 0
    assert float(moved.mean()) < 0.003 and float(moved.max()) < 0.03  # grid spacing 0.025


def test_simplify_bunny_to_target():
    mesh = load(FIXTURES / "bunny.glb")
    out = simplify(mesh, 1000)
    assert 800 <= out.n_faces <= 1100 and out.uvs is not None
    assert simplify(out, 5000) is out  # already below the target


def test_spherical_uv_range():
    points = torch.randn(2000, 3, generator=torch.Generator().manual_seed(0))
    uv = spherical_uv(points)
    assert uv.shape == (2000, 2)
    assert float(uv.min()) >= 0.0 and float(uv.max()) <= 1.0
    top = spherical_uv(torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]))
    assert torch.allclose(top[:, 1], torch.tensor([1.0, 0.0]))  # v = 1 at the north pole (+Z)


def test_vertex_normals_unit_length():
    mesh = load(FIXTURES / "suzanne.glb")
    normals = vertex_normals(mesh.positions, mesh.faces)
    assert torch.allclose(normals.norm(dim=-1), torch.ones(mesh.n_vertices), atol=1e-5)
    # A flat square in the z = 0 plane, wound counter-clockwise seen from +z: normals are +z.
    positions = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    assert torch.allclose(vertex_normals(positions, faces), torch.tensor([0.0, 0, 1]).expand(4, 3))
    # The same square double-sided (each face twinned with the opposite winding): still unit, still +-z.
    twin = torch.cat([faces, faces.flip(-1)])
    normals = vertex_normals(positions, twin)
    assert torch.allclose(normals.abs(), torch.tensor([0.0, 0, 1]).expand(4, 3), atol=1e-6)


def test_latin1_obj_with_non_utf8_material_name_loads(tmp_path):
    (tmp_path / "m.mtl").write_bytes(b"newmtl caf\xe9\nKd 1 0 0\n")
    (tmp_path / "latin.obj").write_bytes(b"mtllib m.mtl\nusemtl caf\xe9\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    mesh = load(tmp_path / "latin.obj")
    assert mesh.n_faces == 1 and mesh.materials[0].name == "caf\u00e9"


@pytest.mark.parametrize("umask", [0o022, 0o077])
def test_saved_files_honour_the_umask(tmp_path, umask):
    """Every file written (OBJ, MTL, textures, a GLB) gets 0666 less the umask, as a plainly created
    file would, not the 0600 of the temporary file it is renamed from."""
    previous = os.umask(umask)
    try:
        written = save(load(FIXTURES / "sh3d_deckChair" / "deckChair.obj"), tmp_path / "chair.obj")
        written += save(load(FIXTURES / "bunny.glb"), tmp_path / "bunny.glb")
        mesh_files.atomic_write(tmp_path / "one.png", b"x")
        from meshseal.models.io import save_tensors

        save_tensors({"w": torch.zeros(2)}, tmp_path / "model.safetensors", {"format": "test"})
    finally:
        os.umask(previous)
    assert len(written) >= 5
    for path in [*written, tmp_path / "one.png", tmp_path / "model.safetensors"]:
        assert (path.stat().st_mode & 0o777) == 0o666 & ~umask, path


@pytest.mark.parametrize("suffix", [".obj", ".glb"])
def test_a_mesh_made_in_memory_keeps_its_material_colours(tmp_path, suffix):
    """A mesh built in memory (no file behind it) is written with its own diffuse colour (and, in an
    OBJ's MTL, its ambient, specular and shininess), not trimesh's defaults."""
    positions = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    faces = torch.tensor([[0, 1, 2]])
    texture = torch.rand(8, 8, 3, generator=torch.Generator().manual_seed(0))
    material = Material(texture=texture, ambient=torch.full((3,), 0.2), diffuse=torch.tensor([0.9, 0.8, 0.7]),
                        specular=torch.full((3,), 0.1), shininess=20.0)
    mesh = Mesh(positions, vertex_normals(positions, faces), faces, positions[:, :2].clone(), materials=[material])
    save(mesh, tmp_path / f"a{suffix}")
    back = load(tmp_path / f"a{suffix}", up_axis="z").materials[0]
    assert torch.allclose(back.diffuse, material.diffuse, atol=1 / 255)
    if suffix == ".obj":
        assert torch.allclose(back.ambient, material.ambient, atol=1 / 255)
        assert torch.allclose(back.specular, material.specular, atol=1 / 255)
        assert back.shininess == pytest.approx(20.0)


def test_subdivision_keeps_the_surface_and_its_texture_mapping():
    """`preprocess.subdivide` cuts every face into four (an edge shared by two faces gets one midpoint)
    and the subdivided bunny renders as the bunny does: the same coverage, the same colours but for
    the normals' interpolation."""
    from meshseal.mesh.preprocess import subdivide
    from meshseal.render import MeshBatch, MeshRenderer, sample_any_lights, sample_any_view_cameras

    mesh = MeshBatch.from_mesh(normalize(to_z_up(load(FIXTURES / "bunny.glb"))))
    positions, normals, uvs, faces = mesh.positions[0], mesh.normals[0], mesh.uvs[0], mesh.faces
    edges = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).sort(1).values.unique(dim=0)
    new_positions, new_normals, new_uvs, new_faces = subdivide(positions, normals, uvs, faces, 1)
    assert len(new_faces) == 4 * len(faces) and len(new_positions) == len(positions) + len(edges)
    assert torch.allclose(new_normals.norm(dim=1), torch.ones(len(new_normals)), atol=1e-5)
    dense = replace(mesh, positions=new_positions[None], normals=new_normals[None], uvs=new_uvs[None], faces=new_faces,
                    face_material=torch.zeros(len(new_faces), dtype=torch.long))
    generator = torch.Generator().manual_seed(0)
    cameras, lights = sample_any_view_cameras(2, generator), sample_any_lights(2, generator)
    before, after = (MeshRenderer()(m, cameras, lights, 96, 96).rgba for m in (mesh, dense))
    assert torch.equal(before[..., 3] > 0.5, after[..., 3] > 0.5)
    assert float((before[..., :3] - after[..., :3]).abs().mean()) < 1e-4  # a UV map shifted by 0.01: 3e-3
    assert subdivide(positions, normals, None, faces, 2)[2] is None and len(subdivide(positions, normals, None, faces, 2)[3]) == 16 * len(faces)
