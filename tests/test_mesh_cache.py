"""The load cache (`meshseal.mesh.cache`): a mesh met before comes back as trimesh loaded it, without
trimesh; a changed input is a new entry; a cache that cannot be used costs nothing but time."""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from meshseal.errors import MeshError
from meshseal.mesh import cache as mesh_cache
from meshseal.mesh import load, save

FIXTURES = Path(__file__).parent / "fixtures"
MESHES = ["bunny.glb", "teapot/teapot.obj", "sh3d_crate/crate.obj", "multi_material.glb", "bunny.ply"]


@pytest.fixture
def cache_folder(tmp_path, monkeypatch):
    folder = tmp_path / "cache"
    monkeypatch.setenv("MESHSEAL_CACHE", str(folder))
    return folder


def same_tensor(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return a.dtype == b.dtype and torch.equal(a, b)


def assert_same_mesh(a, b):
    for name in ("positions", "normals", "faces", "uvs", "face_material"):
        assert same_tensor(getattr(a, name), getattr(b, name)), name
    assert a.up_axis == b.up_axis and len(a.materials) == len(b.materials)
    for x, y in zip(a.materials, b.materials):
        assert x.name == y.name and x.shininess == y.shininess
        for name in ("texture", "ambient", "diffuse", "specular"):
            assert same_tensor(getattr(x, name), getattr(y, name)), name
    assert len(a.source.parts) == len(b.source.parts)
    for p, q in zip(a.source.parts, b.source.parts):
        assert (p.node, p.geometry, p.vertices, p.faces) == (q.node, q.geometry, q.vertices, q.faces)
        assert np.array_equal(p.transform, q.transform)
    assert a.source.input_files == b.source.input_files and a.source.file_type == b.source.file_type
    assert torch.equal(a.source.original_positions, b.source.original_positions)


@pytest.mark.parametrize("name", MESHES)
def test_a_cached_mesh_is_the_mesh_trimesh_loads(cache_folder, name):
    fresh = load(FIXTURES / name)
    first = load(FIXTURES / name, cache=True)  # a miss: loaded with trimesh, then kept
    second = load(FIXTURES / name, cache=True)
    assert first.source.scene is not None and second.source.scene is None
    assert len(list(cache_folder.glob("*.safetensors"))) == 1
    assert_same_mesh(fresh, second)
    assert second.source.path == FIXTURES / name


def test_a_changed_texture_is_a_new_entry(cache_folder, tmp_path):
    folder = tmp_path / "teapot"
    shutil.copytree(FIXTURES / "teapot", folder)
    path = folder / "teapot.obj"
    before = load(path, cache=True)
    textures = [p for p in folder.iterdir() if p.suffix.lower() in {".png", ".jpg", ".jpeg"}]
    assert textures
    image = Image.open(textures[0]).convert("RGB")
    pixels = np.asarray(image).copy()
    pixels[0, 0] = 255 - pixels[0, 0]
    Image.fromarray(pixels).save(textures[0])
    after = load(path, cache=True)
    assert after.source.scene is not None  # not taken from the entry of the old texture
    assert not torch.equal(before.materials[0].texture, after.materials[0].texture)
    assert_same_mesh(load(path), load(path, cache=True))
    assert len(list(cache_folder.glob("*.safetensors"))) == 2


def test_the_up_axis_asked_for_is_part_of_the_key(cache_folder):
    load(FIXTURES / "bunny.glb", cache=True)
    z_up = load(FIXTURES / "bunny.glb", up_axis="z", cache=True)
    assert z_up.source.scene is not None and z_up.up_axis == "z"


def test_off_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv("MESHSEAL_CACHE", "off")
    assert mesh_cache.folder() is None
    for _ in range(2):
        assert load(FIXTURES / "bunny.glb", cache=True).source.scene is not None


def test_a_damaged_entry_is_loaded_again(cache_folder):
    load(FIXTURES / "bunny.glb", cache=True)
    (entry,) = cache_folder.glob("*.safetensors")
    entry.write_bytes(b"not a safetensors file")
    again = load(FIXTURES / "bunny.glb", cache=True)
    assert again.source.scene is not None
    assert_same_mesh(load(FIXTURES / "bunny.glb"), again)
    assert load(FIXTURES / "bunny.glb", cache=True).source.scene is None  # written anew


def test_a_cache_that_cannot_be_written_only_costs_time(tmp_path, monkeypatch):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    monkeypatch.setenv("MESHSEAL_CACHE", str(blocker / "cache"))
    for _ in range(2):
        assert load(FIXTURES / "bunny.glb", cache=True).source.scene is not None


def test_fill_keeps_the_scene_and_fills_the_cache(cache_folder):
    filled = load(FIXTURES / "bunny.glb", cache="fill")
    assert filled.source.scene is not None
    assert load(FIXTURES / "bunny.glb", cache="fill").source.scene is not None  # fill never reads the cache
    assert load(FIXTURES / "bunny.glb", cache=True).source.scene is None


def test_a_cached_mesh_cannot_be_saved(cache_folder, tmp_path):
    load(FIXTURES / "bunny.glb", cache=True)
    cached = load(FIXTURES / "bunny.glb", cache=True)
    with pytest.raises(MeshError, match="load cache"):
        save(cached, tmp_path / "out.glb")
    assert not (tmp_path / "out.glb").exists()


def test_the_least_recently_used_go_past_the_limit(cache_folder, monkeypatch):
    load(FIXTURES / "bunny.glb", cache=True)
    (oldest,) = cache_folder.glob("*.safetensors")
    os.utime(oldest, ns=(1, 1))
    monkeypatch.setattr(mesh_cache, "LIMIT_BYTES", oldest.stat().st_size + 1)
    load(FIXTURES / "teapot/teapot.obj", cache=True)
    assert not oldest.exists() and len(list(cache_folder.glob("*.safetensors"))) == 1


def glb_with(document: dict) -> bytes:
    text = json.dumps(document).encode()
    text += b" " * (-len(text) % 4)
    return b"glTF" + struct.pack("<II", 2, 20 + len(text)) + struct.pack("<I4s", len(text), b"JSON") + text


def test_a_glb_naming_files_outside_itself_is_not_cached():
    assert not mesh_cache.glb_external(glb_with({"buffers": [{"byteLength": 4}], "images": [{"bufferView": 0}]}))
    assert not mesh_cache.glb_external(glb_with({"images": [{"uri": "data:image/png;base64,AAAA"}]}))
    assert mesh_cache.glb_external(glb_with({"images": [{"uri": "texture.png"}]}))
    assert mesh_cache.glb_external(glb_with({"buffers": [{"uri": "mesh.bin", "byteLength": 4}]}))


PROBE = """
import sys
from meshseal.mesh import load
mesh = load(sys.argv[1], cache=True)
print(mesh.source.scene is None, [m for m in ("trimesh", "scipy", "networkx") if m in sys.modules])
"""


def test_a_process_reading_a_cached_mesh_never_imports_trimesh(cache_folder):
    env = dict(os.environ, MESHSEAL_CACHE=str(cache_folder))
    run = [sys.executable, "-c", PROBE, str(FIXTURES / "bunny.glb")]
    first = subprocess.run(run, env=env, capture_output=True, text=True, check=True).stdout.split()
    second = subprocess.run(run, env=env, capture_output=True, text=True, check=True).stdout.strip()
    assert first[0] == "False"
    assert second == "True []"
