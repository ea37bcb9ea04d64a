"""meshseal.data: building a dataset from a folder and from a fake Debian package, no network."""

from __future__ import annotations

import io
import json
import shutil
import struct
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from meshseal.data import MeshDataset, build, dataset_stats
from meshseal.data import sources as S
from meshseal.data.build import assign_split
from meshseal.data.formats import read_ac, read_image, read_off, read_pmd
from meshseal.data.process import ProcessOptions, process_mesh

FIXTURES = Path(__file__).parent / "fixtures"
FACES, TEX = 600, 32


def _make_source(root: Path) -> Path:
    """A small folder of meshes: the fixtures, a ModelNet-like tree and one broken file."""
    import trimesh

    src = root / "src"
    src.mkdir()
    for name in ("bunny.glb", "suzanne.glb", "cube.off", "multi_material.glb", "tetra.stl"):
        if (FIXTURES / name).is_file():
            shutil.copy(FIXTURES / name, src / name)
    for name in ("teapot", "sh3d_crate", "sh3d_deckChair"):
        if (FIXTURES / name).is_dir():
            shutil.copytree(FIXTURES / name, src / name)
    for split, maker in (("train", lambda: trimesh.creation.box((1, 2, 0.5))),
                         ("test", lambda: trimesh.creation.icosphere(2)),
                         ("train", lambda: trimesh.creation.cylinder(0.5, 2.0))):
        folder = src / "chair" / split
        folder.mkdir(parents=True, exist_ok=True)
        mesh = maker()
        index = len(list(folder.iterdir()))
        lines = [f"OFF{len(mesh.vertices)} {len(mesh.faces)} 0"]  # ModelNet's header quirk
        lines += [" ".join(f"{v:.6f}" for v in p) for p in mesh.vertices]
        lines += ["3 " + " ".join(str(i) for i in f) for f in mesh.faces]
        (folder / f"chair_{index:04d}.off").write_text("\n".join(lines) + "\n")
    (src / "broken.obj").write_text("this is not a mesh\n")
    return src


def _build(src: Path, out: Path, seed: int = 0, workers: int = 0, **kwargs):
    """A build in this process (workers=0), or in spawned workers as the command line builds."""
    return build(out, sources=[], texture_sources=[], from_folder=src, textures_dir=FIXTURES / "textures",
                 seed=seed, n_faces=FACES, texture_size=TEX, workers=workers, license_="CC0-1.0", **kwargs)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    src = _make_source(root)
    report = _build(src, root / "out", workers=1)  # the process pool's path; the other builds run in-process
    return src, root / "out", report


def test_build_writes_items_manifest_and_split(built):
    src, out, report = built
    rows = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    assert len(rows) == report["n_built"] >= 8
    assert report["n_skipped"] == 1 and sum(report["skip_reasons"].values()) == 1
    assert "broken" in (out / "failed.jsonl").read_text()
    for row in rows:
        for key in ("id", "source", "source_version", "original_path", "category", "creator", "license",
                    "n_verts", "n_faces", "texture_kind", "split"):
            assert key in row
        assert row["texture_kind"] in ("own", "real", "noise")
        assert (out / row["file"]).is_file() and (out / row["texture_file"]).is_file()
        assert 0 < row["n_faces"] <= FACES and 0 < row["n_verts"] <= FACES
    by_path = {r["original_path"]: r for r in rows}
    assert by_path["chair/test/chair_0000.off"]["split"] == "test"  # train/test folders are honoured
    assert by_path["chair/train/chair_0000.off"]["split"] == "train"
    assert by_path["chair/train/chair_0000.off"]["category"] == "chair"
    groups = {}
    for r in rows:
        groups.setdefault(r["group"], set()).add(r["split"])
    assert all(len(s) == 1 for g, s in groups.items() if not g.startswith("dir/chair"))
    assert (out / "manifest.csv").read_text().startswith("id,split,")
    train = (out / "splits" / "train.txt").read_text().split()
    test = (out / "splits" / "test.txt").read_text().split()
    assert len(train) + len(test) == len(rows) and not set(train) & set(test)
    assert {r["texture_kind"] for r in rows} >= {"own"}


def test_items_are_fixed_size_normalised_z_up(built):
    _, out, _ = built
    for npz in sorted((out / "meshes").glob("*.npz")):
        with np.load(npz) as data:
            assert data["positions"].shape == (FACES, 3) and data["positions"].dtype == np.float32
            assert data["normals"].shape == (FACES, 3) and data["uvs"].shape == (FACES, 2)
            assert data["faces"].shape == (FACES, 3) and data["faces"].dtype == np.int32
            nv, nf = int(data["n_verts"]), int(data["n_faces"])
            pos = data["positions"][:nv]
            assert np.abs(pos).max() <= 1.0 + 1e-5 and np.isclose(np.abs(pos).max(), 1.0, atol=1e-4)
            assert (data["faces"][nf:] == 0).all() and data["faces"][:nf].max() < nv
            normals = data["normals"][:nv]
            assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-4)
    # the box (1 x 2 x 0.5 in an OFF file: Z-up already) keeps its proportions and orientation
    rows = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    box = next(r for r in rows if r["original_path"] == "chair/train/chair_0000.off")
    with np.load(out / box["file"]) as data:
        extent = np.ptp(data["positions"][:int(data["n_verts"])], axis=0)
    assert np.allclose(extent, [1.0, 2.0, 0.5], atol=1e-4)


def test_y_up_source_is_rotated_to_z_up(tmp_path):
    import trimesh

    src = tmp_path / "src"
    src.mkdir()
    trimesh.creation.box((1.0, 2.0, 0.5)).export(src / "tall.obj")  # OBJ: Y is up
    _build(src, tmp_path / "out")
    with np.load(next((tmp_path / "out" / "meshes").glob("*.npz"))) as data:
        extent = np.ptp(data["positions"][:int(data["n_verts"])], axis=0)
    assert np.allclose(extent, [1.0, 0.5, 2.0], atol=1e-4)  # (x, y, z) -> (x, -z, y)


def test_stats_json_and_cli(built, capsys):
    from meshseal.data.cli import main

    _, out, _ = built
    stats = dataset_stats(out)
    for key in ("n_train", "n_test", "n_textures", "n_categories"):
        assert isinstance(stats[key], int)
    assert stats["n_train"] + stats["n_test"] == stats["n_items"]
    assert stats["n_textures"] == 3
    run = subprocess.run([sys.executable, "-m", "meshseal.data.cli", "data", "stats", str(out), "--json"],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    parsed = json.loads(run.stdout)
    assert parsed["n_train"] == stats["n_train"] and parsed["n_test"] == stats["n_test"]
    capsys.readouterr()
    assert main(["data", "stats", str(out)]) == 0  # the text form, in this process
    text = capsys.readouterr().out
    assert "train" in text and "category" in text


def test_cli_bad_input_is_one_line(tmp_path):
    for argv in (["data", "stats", str(tmp_path / "missing")],
                 ["data", "build", "--from-folder", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]):
        run = subprocess.run([sys.executable, "-m", "meshseal.data.cli", *argv], capture_output=True, text=True,
                             timeout=120)
        assert run.returncode != 0
        lines = [line for line in run.stderr.splitlines() if line.strip()]
        assert len(lines) == 1 and "Traceback" not in run.stderr, run.stderr


def test_register_adds_data_command():
    import argparse

    from meshseal.data.cli import register

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["data", "stats", "x", "--json"])
    assert callable(args.func) and args.json
    args = parser.parse_args(["data", "build", "--out", "d", "--faces", "100", "--seed", "3"])
    assert args.faces == 100 and args.seed == 3


def test_dataset_tensors_and_batches(built):
    _, out, _ = built
    dataset = MeshDataset(out, split="all")
    item = dataset[0]
    assert item["positions"].shape == (FACES, 3) and item["positions"].dtype == torch.float32
    assert item["normals"].shape == (FACES, 3) and item["uvs"].shape == (FACES, 2)
    assert item["faces"].shape == (FACES, 3) and item["faces"].dtype == torch.int64
    assert item["texture"].shape == (3, TEX, TEX) and 0.0 <= float(item["texture"].min())
    assert float(item["texture"].max()) <= 1.0
    assert isinstance(item["id"], str) and int(item["n_verts"]) > 0
    batch = next(iter(torch.utils.data.DataLoader(dataset, batch_size=4)))
    assert batch["positions"].shape == (4, FACES, 3) and batch["texture"].shape == (4, 3, TEX, TEX)
    assert len(MeshDataset(out, "train")) + len(MeshDataset(out, "test")) == len(dataset)
    assert len(MeshDataset(out, "test_cc0")) == len(MeshDataset(out, "test"))  # all CC0 here


def test_dataset_retexturing_per_epoch(built):
    _, out, _ = built
    stored = MeshDataset(out, split="all")
    fresh = MeshDataset(out, split="all", retexture=1.0, seed=5)
    again = MeshDataset(out, split="all", retexture=1.0, seed=5)
    a = fresh[0]["texture"]
    assert torch.equal(a, again[0]["texture"])  # same seed and epoch -> same texture
    assert not torch.equal(a, stored[0]["texture"])
    fresh.set_epoch(1)
    assert not torch.equal(a, fresh[0]["texture"])
    assert torch.equal(fresh[0]["positions"], stored[0]["positions"])


def test_same_seed_same_dataset_and_resume(built, tmp_path):
    src, out, report = built
    out2 = tmp_path / "again"
    _build(src, out2)
    assert (out / "manifest.jsonl").read_text() == (out2 / "manifest.jsonl").read_text()
    for npz in (out / "meshes").glob("*.npz"):
        with np.load(npz) as a, np.load(out2 / "meshes" / npz.name) as b:
            for key in ("positions", "uvs", "faces"):
                assert np.array_equal(a[key], b[key])
        assert (out / "textures" / f"{npz.stem}.png").read_bytes() == \
            (out2 / "textures" / f"{npz.stem}.png").read_bytes()
    # resume: everything is kept; a deleted item is rebuilt; the broken asset is not retried
    victim = sorted((out2 / "meshes").glob("*.npz"))[0]
    victim.unlink()
    again = _build(src, out2)
    assert again["n_resumed"] == report["n_built"] - 1 and again["n_built"] == report["n_built"]
    assert victim.is_file()
    # another seed: other noise/real picks
    out3 = tmp_path / "seed1"
    _build(src, out3, seed=1)
    differ = [p.name for p in (out / "textures").glob("*.png")
              if (out3 / "textures" / p.name).read_bytes() != p.read_bytes()]
    rows = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    if any(r["texture_kind"] != "own" for r in rows):
        assert differ


def test_other_settings_are_refused(built):
    src, out, _ = built
    with pytest.raises(S.DataError):
        build(out, sources=[], texture_sources=[], from_folder=src, n_faces=FACES + 1, texture_size=TEX)


# ------------------------------------------------------------------ a fake Debian package (no network)


def _fake_deb(path: Path, members: dict[str, bytes]) -> None:
    """A .deb (ar archive with a data.tar.xz) holding `members`."""
    data = io.BytesIO()
    with tarfile.open(fileobj=data, mode="w:xz") as archive:
        for name, payload in members.items():
            info = tarfile.TarInfo(f"./{name}")
            info.size = len(payload)
            archive.addfile(info, io.BytesIO(payload))
    entries = [("debian-binary", b"2.0\n"), ("control.tar.xz", b""), ("data.tar.xz", data.getvalue())]
    with open(path, "wb") as handle:
        handle.write(b"!<arch>\n")
        for name, payload in entries:
            handle.write(f"{name:<16}{0:<12}{0:<6}{0:<6}{100644:<8}{len(payload):<10}`\n".encode())
            handle.write(payload + (b"\n" if len(payload) % 2 else b""))


def test_sweethome3d_source_from_fake_package(tmp_path, monkeypatch):
    sh3f = io.BytesIO()
    props = ["id=SweetHome3D#BlendSwap-CC-0-Models", "license=Public domain"]
    with zipfile.ZipFile(sh3f, "w") as archive:
        for index, name in enumerate(("sh3d_crate", "sh3d_deckChair"), start=1):
            for f in (FIXTURES / name).iterdir():
                archive.write(f, f"blendswap-cc-0/{name}/{f.name}")
            obj = next((FIXTURES / name).glob("*.obj")).name
            props += [f"name#{index}={'Crate' if 'crate' in name else 'Deck chair'}", f"category#{index}=Misc",
                      f"model#{index}=/blendswap-cc-0/{name}/{obj}", f"creator#{index}=Creator{index}"]
        archive.writestr("PluginFurnitureCatalog.properties", "\n".join(props) + "\n")
    cache = tmp_path / "cache"
    cache.mkdir()
    _fake_deb(cache / "sweethome3d-furniture_9.9-1_all.deb",
              {"usr/share/sweethome3d/furniture/BlendSwap-CC-0.sh3f": sh3f.getvalue()})
    monkeypatch.setattr(shutil, "which", lambda name: None)  # use the pure-Python .deb reader
    assets, textures = S.sweethome3d_source(cache, log=lambda *a: None)
    assert [a.name for a in assets] == ["Crate", "Deck chair"]
    assert assets[1].category == "chair" and assets[0].license == "CC0-1.0"
    assert assets[0].source_version == "9.9-1" and assets[0].group == "sh3d/BlendSwap-CC-0/Creator1"
    assert len(textures) >= 2
    monkeypatch.undo()
    report = build(tmp_path / "out", sources=["sweethome3d"], texture_sources=["sweethome3d"], cache=cache,
                   n_faces=FACES, texture_size=TEX, workers=0, pool_size=10)
    assert report["n_built"] == 2 and report["n_textures"] >= 2
    rows = [json.loads(line) for line in (tmp_path / "out" / "manifest.jsonl").read_text().splitlines()]
    assert {r["texture_kind"] for r in rows} == {"own"}
    assert all(r["source"] == "sweethome3d-furniture" and r["creator"].startswith("Creator") for r in rows)


def test_missing_package_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setattr(shutil, "which", lambda name: None)
    with pytest.raises(S.DataError, match="apt-get"):
        S.fetch_deb("no-such-package", tmp_path)


# ------------------------------------------------------------------ readers and helpers


def test_read_ac_hierarchy_and_uvs(tmp_path):
    (tmp_path / "t.ac").write_text("""AC3Db
MATERIAL "red" rgb 1 0 0  amb 0.2 0.2 0.2  emis 0 0 0  spec 0 0 0  shi 10  trans 0
OBJECT world
kids 1
OBJECT poly
name "quad"
loc 1 0 0
numvert 4
0 0 0
1 0 0
1 1 0
0 1 0
numsurf 2
SURF 0x0
mat 0
refs 4
0 0 0
1 1 0
2 1 1
3 0 1
SURF 0x2
mat 0
refs 2
0 0 0
1 1 0
kids 0
""")
    raw = read_ac(tmp_path / "t.ac")
    assert raw.faces.shape == (2, 3) and raw.up_axis == "y"
    assert np.allclose(raw.positions[:, 0].min(), 1.0)  # loc applied
    assert np.allclose(raw.materials[0].diffuse, [1, 0, 0]) and raw.uvs is None


def test_read_pmd_synthetic():
    vertices = [((0, 0, 0), (0, 1, 0), (0.0, 0.0)), ((1, 0, 0), (0, 1, 0), (1.0, 0.0)),
                ((0, 0, 1), (0, 1, 0), (0.0, 1.0))]
    body = struct.pack("<II", 3, 1)  # numVertices, numTexCoords (version 4)
    for pos, normal, uv in vertices:
        body += struct.pack("<3f3f2f4B4f", *pos, *normal, *uv, 255, 255, 255, 255, 0, 0, 0, 0)
    body += struct.pack("<I3H", 1, 0, 1, 2) + struct.pack("<II", 0, 0)
    data = b"PSMD" + struct.pack("<II", 4, len(body)) + body
    texture = np.zeros((4, 4, 3), np.uint8)
    raw = read_pmd(data, "x.pmd", texture)
    assert raw.faces.tolist() == [[0, 1, 2]] and np.allclose(raw.positions[2], [0, 0, 1])
    assert np.allclose(raw.uvs[:, 1], [1.0, 1.0, 0.0])  # v flipped to OpenGL convention
    with pytest.raises(Exception):
        read_pmd(b"NOPE" + data[4:], "bad.pmd")


def test_read_sgi_rle():
    header = bytearray(512)
    header[0:2] = struct.pack(">h", 474)
    header[2], header[3] = 1, 1
    header[4:12] = struct.pack(">HHHH", 3, 2, 2, 1)
    rows = [bytes([0x02, 10]) + b"\x00", bytes([0x82, 20, 30]) + b"\x00"]
    offset = 512 + 16
    starts, lengths, body = [], [], b""
    for row in rows:
        starts.append(offset + len(body))
        lengths.append(len(row))
        body += row
    data = bytes(header) + struct.pack(">2I", *starts) + struct.pack(">2I", *lengths) + body
    image = read_image(data, "t.rgb")
    assert image.shape == (2, 2, 3)
    assert image[1, :, 0].tolist() == [10, 10] and image[0, :, 0].tolist() == [20, 30]  # bottom-up rows



def test_read_image_checks_are_the_mesh_readers(tmp_path):
    """Image decoding goes through mesh.validate.read_image: a non-file or non-image is a one-line MeshError."""
    from meshseal.errors import MeshError

    with pytest.raises(MeshError, match="is a directory"):
        read_image(tmp_path)
    with pytest.raises(MeshError, match="not a readable image"):
        read_image(b"not an image", "x.png")
    rgba = np.zeros((4, 4, 4), np.uint8)  # fully transparent black
    buffer = io.BytesIO()
    Image.fromarray(rgba, "RGBA").save(buffer, format="PNG")
    assert (read_image(buffer.getvalue()) == 255).all()  # composited on white
    assert (read_image(buffer.getvalue(), alpha="drop") == 0).all()


def test_double_sided_sheet_gets_its_normal():
    """A sheet whose every triangle is twinned with the opposite winding still gets its plane's normal."""
    from meshseal.data.formats import RawMaterial, RawMesh

    positions = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]], float)  # the y = 0 plane
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    raw = RawMesh(positions, np.concatenate([faces, faces[:, ::-1]]), None, np.zeros(4, np.int64), [RawMaterial()], "z")
    item = process_mesh(raw, ProcessOptions(n_faces=64, max_verts=64, texture_size=8), np.random.default_rng(0))
    normals = item.normals[:item.n_verts]
    assert np.allclose(np.abs(normals[:, 1]), 1.0, atol=1e-6)

def test_off_reader_header_variants(tmp_path):
    (tmp_path / "a.off").write_text("OFF\n# comment\n4 2 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n3 0 1 2 255 0 0\n")
    raw = read_off(tmp_path / "a.off")
    assert raw.faces.shape == (3, 3) and raw.up_axis == "z"
    (tmp_path / "b.off").write_text("OFF\n4 2 0\n0 0 0\n")
    with pytest.raises(Exception, match="malformed"):
        read_off(tmp_path / "b.off")


def test_multi_material_atlas_keeps_colours():
    from meshseal.data.formats import RawMaterial, RawMesh

    positions = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]])
    uvs = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [1, 0], [1, 1]], float)
    checker = np.zeros((8, 8, 3), np.uint8)
    checker[::2, ::2] = 255
    materials = [RawMaterial("tex", checker), RawMaterial("blue", None, np.array([0, 0, 1], np.float32))]
    raw = RawMesh(positions, faces, uvs, np.array([0, 0, 1, 1]), materials, "z")
    item = process_mesh(raw, ProcessOptions(n_faces=64, max_verts=64, texture_size=32),
                        np.random.default_rng(0))
    assert item.texture_kind == "own" and item.n_faces == 64
    # blue swatch present, and the blue faces' uvs sample it
    u, v = item.uvs[:item.n_verts].T
    px = np.clip((u * 32).astype(int), 0, 31), np.clip(((1 - v) * 32).astype(int), 0, 31)
    colours = item.texture[px[1], px[0]]
    assert (colours == [0, 0, 255]).all(axis=1).sum() > 0


def test_split_keeps_groups_together_and_cc0_subset():
    assets = []
    for g in range(40):
        for k in range(5):
            assets.append(S.Asset(id=f"a{g}-{k}", source="s", source_version="1", original_path="", path="",
                                  name="", category="chair", source_category="", creator=f"c{g}",
                                  license="CC0-1.0" if g < 10 else "CC-BY-3.0", group=f"g{g}"))
    split = assign_split(assets, seed=0, test_fraction=0.2)
    assert split == assign_split(assets, seed=0, test_fraction=0.2)
    n_test = sum(v == "test" for v in split.values())
    assert 0.1 * len(assets) <= n_test <= 0.3 * len(assets)
    for g in range(40):
        assert len({split[f"a{g}-{k}"] for k in range(5)}) == 1
    assert any(split[f"a{g}-0"] == "test" for g in range(10))  # some CC0 in test
    assert split != assign_split(assets, seed=1, test_fraction=0.2)


def test_categorize():
    assert S.categorize("Armchair") == "chair"
    assert S.categorize("Office desk") == "desk"
    assert S.categorize("coconutTree") == "plant"
    assert S.categorize("HighriseGrey", "Residential") == "building"
    assert S.categorize("zzz") == "other"
