"""The `meshseal` command line: render and info on every fixture, and one-line errors on bad input."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from meshseal import __version__
from meshseal.cli import main

FIXTURES = Path(__file__).parent / "fixtures"
MESHES = ["bunny.glb", "suzanne.glb", "multi_material.glb", "bunny.ply", "cube.off", "tetra.stl",
          "teapot/teapot.obj", "sh3d_crate/crate.obj", "sh3d_deckChair/deckChair.obj"]


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code: int, err: str) -> None:
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("meshseal: error: "), err
    assert "Traceback" not in err


@pytest.mark.parametrize("name", MESHES)
def test_render_every_fixture(name, tmp_path, capsys):
    out = tmp_path / "image.png"
    code, stdout, err = run(capsys, "render", FIXTURES / name, "-o", out, "--width", 64, "--height", 48)
    assert code == 0, err
    image = np.asarray(Image.open(out))
    assert image.shape == (48, 64, 3)
    foreground = image.max(axis=-1) > 0
    assert 0.02 < foreground.mean() < 0.95  # the object is in view and framed
    assert np.percentile(image[foreground].max(axis=-1), 90) > 30  # lit, not black
    assert str(out) in stdout
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_render_is_textured_and_upright(tmp_path, capsys):
    # The bunny: green grass texture; its ears (the top of the Y-up file) at the top of the image.
    out = tmp_path / "bunny.png"
    assert run(capsys, "render", FIXTURES / "bunny.glb", "-o", out, "--width", 96, "--height", 96,
               "--blend", "hard")[0] == 0
    image = np.asarray(Image.open(out)).astype(float)
    foreground = image.max(axis=-1) > 0
    assert image[foreground][:, 1].mean() > 1.5 * image[foreground][:, 0].mean()  # green
    assert image[foreground].std(axis=0).mean() > 5  # textured and shaded, not flat
    rows = np.nonzero(foreground.any(axis=1))[0]
    # Flipping the up axis puts the bunny on its back: a different silhouette.
    flipped = tmp_path / "bunny_z.png"
    assert run(capsys, "render", FIXTURES / "bunny.glb", "-o", flipped, "--width", 96, "--height", 96,
               "--blend", "hard", "--up", "z")[0] == 0
    assert not np.array_equal(np.asarray(Image.open(flipped)), image.astype(np.uint8))
    assert rows.min() > 0 and rows.max() < 95  # framed with a margin


def test_render_views_seed_and_options(tmp_path, capsys):
    out = tmp_path / "view.png"
    code, stdout, err = run(capsys, "render", FIXTURES / "suzanne.glb", "-o", out, "--views", 3, "--seed", 4,
                            "--width", 32, "--height", 32)
    assert code == 0, err
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["view_0.png", "view_1.png", "view_2.png"]
    first = [np.asarray(Image.open(tmp_path / n)) for n in names]
    assert not np.array_equal(first[0], first[1])
    # Same seed -> same images; the any-view sampler gives other views.
    again = tmp_path / "again"
    run(capsys, "render", FIXTURES / "suzanne.glb", "-o", again / "view.png", "--views", 3, "--seed", 4,
        "--width", 32, "--height", 32)
    assert all(np.array_equal(a, np.asarray(Image.open(again / n))) for a, n in zip(first, names))
    other = tmp_path / "other"
    assert run(capsys, "render", FIXTURES / "suzanne.glb", "-o", other / "v.png", "--views", 2, "--seed", 4,
               "--sampler", "any", "--width", 32, "--height", 32)[0] == 0
    assert len(list(other.iterdir())) == 2
    # Explicit camera, light, background.
    single = tmp_path / "single.png"
    code, _, err = run(capsys, "render", FIXTURES / "cube.off", "-o", single, "--camera", "0,-4,0.5",
                       "--light", "1,-3,2", "--background", "0,0,1", "--width", 32, "--height", 32)
    assert code == 0, err
    image = np.asarray(Image.open(single))
    assert tuple(image[0, 0]) == (0, 0, 255)
    # A camera straight above still works (a different up vector is used).
    assert run(capsys, "render", FIXTURES / "cube.off", "-o", tmp_path / "top.png", "--camera", "0,0,4",
               "--width", 16, "--height", 16)[0] == 0


def test_render_never_overwrites_the_input(tmp_path, capsys):
    folder = tmp_path / "crate"
    shutil.copytree(FIXTURES / "sh3d_crate", folder)
    (folder / "crate.png").write_bytes((folder / "crate.jpg").read_bytes())
    (folder / "crate.mtl").write_text((folder / "crate.mtl").read_text().replace("crate.jpg", "crate.png"))
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    # The OBJ's own texture as the output:
    assert_one_line_error(*run(capsys, "render", folder / "crate.obj", "-o", folder / "crate.png")[::2])
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before


@pytest.mark.parametrize("name", ["bunny.glb", "multi_material.glb", "sh3d_deckChair/deckChair.obj", "cube.off"])
def test_info_json(name, capsys):
    code, out, err = run(capsys, "info", FIXTURES / name, "--json")
    assert code == 0, err
    lines = out.strip().splitlines()
    assert len(lines) == 1
    info = json.loads(lines[0])
    assert {"vertices", "faces", "parts", "materials", "uvs", "normals", "up_axis", "bounds"} <= set(info)
    assert info["vertices"] > 0 and info["faces"] > 0
    assert len(info["bounds"]["min"]) == 3 and all(a <= b for a, b in zip(info["bounds"]["min"],
                                                                             info["bounds"]["max"]))
    if name == "multi_material.glb":
        assert info["faces"] == 1152 and len(info["parts"]) == 3
        textures = [m["texture"] for m in info["materials"]]
        assert sorted(t["width"] for t in textures if t) == [200, 256] and textures.count(None) == 1
        assert info["uvs"] is True and info["up_axis"] == "y"
    if name == "cube.off":
        assert info["uvs"] is False and info["up_axis"] == "z"
        assert info["bounds"] == {"min": [-1.0, -1.0, -1.0], "max": [1.0, 1.0, 1.0]}


def test_info_text(capsys):
    code, out, _ = run(capsys, "info", FIXTURES / "sh3d_deckChair" / "deckChair.obj")
    assert code == 0
    assert "faces:     1152" in out and "ChairFrame: texture 200x200" in out and "Metal: no texture" in out


def _bad_inputs(tmp_path: Path) -> list[list]:
    garbage = tmp_path / "garbage.obj"
    garbage.write_bytes(np.random.default_rng(0).bytes(2048))
    truncated = tmp_path / "cut.glb"
    truncated.write_bytes((FIXTURES / "bunny.glb").read_bytes()[:5000])
    png = tmp_path / "picture.obj"
    png.write_bytes((FIXTURES / "textures" / "brick.png").read_bytes())
    empty = tmp_path / "empty.stl"
    empty.write_bytes(b"")
    out = tmp_path / "out.png"
    return [
        ["render", tmp_path / "missing.glb", "-o", out],
        ["render", garbage, "-o", out],
        ["render", truncated, "-o", out],
        ["render", png, "-o", out],
        ["render", empty, "-o", out],
        ["render", FIXTURES / "textures" / "brick.png", "-o", out],  # unsupported extension
        ["render", FIXTURES / "bunny.glb", "-o", tmp_path / "out.bmp"],
        ["render", FIXTURES / "bunny.glb", "-o", out, "--camera", "1,2"],
        ["render", FIXTURES / "bunny.glb", "-o", out, "--camera", "0,0,0"],
        ["render", FIXTURES / "bunny.glb", "-o", out, "--width", "0"],
        ["render", FIXTURES / "bunny.glb", "-o", out, "--background", "red"],
        ["render", FIXTURES / "bunny.glb", "-o", out, "--views", "2", "--camera", "0,-3,2"],
        ["render", FIXTURES / "bunny.glb", "-o", tmp_path],  # a directory
        ["render", FIXTURES / "bunny.glb"],  # no -o
        ["info", tmp_path / "missing.obj"],
        ["info", garbage, "--json"],
        ["no-such-command"],
        [],
    ]


def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    for argv in _bad_inputs(tmp_path):
        code, out, err = run(capsys, *argv)
        if argv:
            assert_one_line_error(code, err)
        else:
            assert code == 2 and "Traceback" not in err  # no command: the help, exit 2
    assert not (tmp_path / "out.png").exists()


def test_version_and_help(capsys):
    code, out, _ = run(capsys, "--version")
    assert code == 0 and __version__ in out
    code, out, _ = run(capsys, "render", "--help")
    assert code == 0 and "--views" in out and "--sampler" in out


def _console(*argv, **kwargs) -> subprocess.CompletedProcess:
    executable = Path(sys.executable).with_name("meshseal")
    command = [str(executable)] if executable.exists() else [sys.executable, "-m", "meshseal.cli"]
    return subprocess.run(command + [str(a) for a in argv], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "MESHSEAL_DEBUG": ""}, **kwargs)


def test_console_script(tmp_path):
    result = _console("render", FIXTURES / "teapot" / "teapot.obj", "-o", tmp_path / "t.png", "--width", 24,
                      "--height", 24)
    assert result.returncode == 0, result.stderr
    assert Image.open(tmp_path / "t.png").size == (24, 24)
    bad = _console("info", tmp_path / "t.png")  # a PNG is not a mesh
    assert bad.returncode == 2
    assert bad.stderr.count("\n") == 1 and bad.stderr.startswith("meshseal: error: ")
    assert "Traceback" not in bad.stderr


def test_output_folder_is_created_and_removed_again_on_failure(tmp_path, capsys, monkeypatch):
    # Policy: a missing output folder is created (like mkdir -p); if writing fails, it is removed again.
    out = tmp_path / "new" / "deeper" / "view.png"
    assert run(capsys, "render", FIXTURES / "cube.off", "-o", out, "--width", 16, "--height", 16)[0] == 0
    assert out.is_file()
    from meshseal.mesh import io as mesh_io

    def failing_replace(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(mesh_io.os, "replace", failing_replace)
    code, _, err = run(capsys, "render", FIXTURES / "cube.off", "-o", tmp_path / "other" / "v.png", "--width", 16,
                       "--height", 16)
    assert_one_line_error(code, err)
    assert "v.png: cannot write: No space left on device" in err
    assert not (tmp_path / "other").exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_output_folder_is_one_line_error(tmp_path, capsys):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        code, _, err = run(capsys, "render", FIXTURES / "cube.off", "-o", locked / "v.png")
        assert_one_line_error(code, err)
        assert "not writable" in err and not list(locked.iterdir())
    finally:
        locked.chmod(0o755)


def test_output_hard_linked_to_the_input_is_refused(tmp_path, capsys):
    glb = tmp_path / "bunny.glb"
    shutil.copy(FIXTURES / "bunny.glb", glb)
    os.link(glb, tmp_path / "link.glb")
    code, _, err = run(capsys, "embed", glb, "-o", tmp_path / "link.glb", "--bits", "01" * 32)
    assert_one_line_error(code, err)
    assert "refusing to overwrite an input file" in err
    assert glb.read_bytes() == (FIXTURES / "bunny.glb").read_bytes()


@pytest.mark.parametrize("name", ["bunny.glb", "sh3d_deckChair/deckChair.obj", "suzanne.glb"])
def test_default_view_frames_the_object_and_lights_the_side_it_sees(name, tmp_path, capsys):
    """The default view spans ~70 % of the frame, centred, and its key light sits beside the camera:
    the object is brighter than under the seed's mean light (2, 1, 2) from the seed's camera."""
    out, seed = tmp_path / "default.png", tmp_path / "seed.png"
    assert run(capsys, "render", FIXTURES / name, "-o", out, "--width", 128, "--height", 96, "--blend", "hard")[0] == 0
    assert run(capsys, "render", FIXTURES / name, "-o", seed, "--width", 128, "--height", 96, "--blend", "hard",
               "--camera", "0,-2.5,3", "--light", "2,1,2")[0] == 0
    image = np.asarray(Image.open(out)).astype(float)
    foreground = image.max(axis=-1) > 0
    rows, columns = np.nonzero(foreground.any(axis=1))[0], np.nonzero(foreground.any(axis=0))[0]
    height, width = rows.max() - rows.min() + 1, columns.max() - columns.min() + 1
    assert 0.64 <= max(height / 96, width / 128) <= 0.74, (height, width)  # the larger share of the frame
    assert abs((rows.max() + rows.min()) / 2 - 47.5) < 4 and abs((columns.max() + columns.min()) / 2 - 63.5) < 4
    before = np.asarray(Image.open(seed)).astype(float)
    assert image[foreground].mean() > 1.1 * before[before.max(axis=-1) > 0].mean()


def test_eval_reads_a_folder_of_the_users_own_meshes(tmp_path, capsys):
    """`meshseal eval --data FOLDER`: each textured single-material mesh of the folder marked, rendered,
    attacked and read as `detect` reads it; the others left out, each said why; without --attacks or
    --register, or without a usable mesh, a one-line error."""
    shutil.copy(FIXTURES / "bunny.glb", tmp_path / "bunny.glb")
    shutil.copy(FIXTURES / "tetra.stl", tmp_path / "tetra.stl")
    shutil.copy(FIXTURES / "multi_material.glb", tmp_path / "multi_material.glb")
    code, out, err = run(capsys, "eval", "--data", tmp_path, "--views", 1, "--size", 128, "--attacks", "none,jpeg90",
                         "--json")
    assert code == 0, err
    result = json.loads(out)
    assert result["n_meshes"] == 1 and result["split"] == "folder" and result["attacks"]["none"]["pictures"] == 1
    assert result["attacks"]["none"]["detected"] == 1.0 and result["attacks"]["jpeg90"]["pictures"] == 1
    assert list(result["by_item"]) == ["bunny.glb"] and result["by_item"]["bunny.glb"]["none"] == 1.0
    assert "tetra.stl: left out: no texture" in err and "multi_material.glb: left out: 3 materials" in err
    assert_one_line_error(*run(capsys, "eval", "--data", tmp_path)[::2])
    (tmp_path / "bunny.glb").unlink()
    assert_one_line_error(*run(capsys, "eval", "--data", tmp_path, "--attacks", "none")[::2])


def test_detect_quick_registers_without_the_recut_and_the_retry(tmp_path, capsys, monkeypatch):
    """`detect --quick` (a scan) hands `quick` to registration, which then neither cuts the object again
    nor tries more views (tests/test_registration_speed.py); without it the full registration runs. The
    picture of the mesh, without metadata, is read either way."""
    import meshseal.reading.registration as registration

    seen = []
    full = registration.register_with_masks

    def recording(*args, quick=False, **kwargs):
        seen.append(quick)
        return full(*args, quick=quick, **kwargs)

    monkeypatch.setattr(registration, "register_with_masks", recording)
    picture = tmp_path / "bunny.png"
    assert run(capsys, "render", FIXTURES / "bunny.glb", "-o", picture, "--width", 128, "--height", 128)[0] == 0
    Image.open(picture).convert("RGB").save(tmp_path / "bare.png")  # no camera in the file
    for flags, expected in (([], False), (["--quick"], True)):
        code, out, err = run(capsys, "detect", tmp_path / "bare.png", "--mesh", FIXTURES / "bunny.glb", "--json", *flags)
        assert code == 1, err  # the unmarked bunny: read, no mark
        assert json.loads(out)["camera"].startswith("registered") and seen[-1] is expected


def _web_table():
    """`tools/web_table.py` as a module (tools/ is not a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("web_table", FIXTURES.parents[1] / "tools" / "web_table.py")
    web_table = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(web_table)
    return web_table


def test_the_web_table_runs_each_part_in_slices_and_judges_every_row_against_its_target(capsys, monkeypatch):
    """`tools/web_table.py` (issue #45's table in one command): one `meshseal eval` process a slice of
    each part, and a row is met only where every part that measured it meets its target (the clean
    pictures' exact message too)."""
    import sys

    web_table = _web_table()
    monkeypatch.setattr(sys, "argv", ["web_table.py", "--data", "data", "--work", "w", "--meshes", "60",
                                      "--slice", "25", "--dry-run"])
    assert web_table.main() == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 3 + 3 + 1 + 1  # 3 slices of each test part, one of each fixture part
    assert sum("--start 25 --meshes 25" in line for line in lines) == 2 and sum("--meshes 10" in line for line in lines) == 2
    assert sum("--register" in line for line in lines) == 4

    def row(detected, exact=0.5):
        return {"pictures": 10, "detected": detected, "exact": exact}

    merged = {"known": {"flip_object": 0.02, "flip_object_p95": 0.06, "psnr_object": 45.0, "psnr_texture_shown": 40.2,
                        "attacks": {"none": row(0.98, 0.96), "jpeg50": row(0.71)}},
              "registered": {"attacks": {"none": row(0.99, 0.90), "jpeg50": row(0.75)}}}
    table = {line.split(" | ")[0].lstrip("| "): line for line in web_table.target_table(merged).splitlines()}
    assert table["object FLIP, mean"].endswith("| yes |") and table["object FLIP, p95"].endswith("| no |")
    assert table["jpeg50: detected (exact)"].endswith("| yes |")
    assert table["none: detected (exact)"].endswith("| no |")  # the registered exact message 0.90 < 0.95


def test_the_web_table_keeps_each_slice_with_the_users_umask_and_leaves_no_temporary(tmp_path):
    """A slice's JSON is replaced whole (never half written, so a resumed run never reads a torn file)
    and gets the mode the user's umask gives a new file, not the 0600 of a temporary file."""
    import os

    web_table = _web_table()
    old = os.umask(0o027)
    try:
        out = tmp_path / "known_0000.json"
        web_table.write_atomically(out, '{"a": 1}')
        web_table.write_atomically(out, '{"a": 2}')
    finally:
        os.umask(old)
    assert out.read_text() == '{"a": 2}'
    assert (out.stat().st_mode & 0o777) == 0o640
    assert [p.name for p in tmp_path.iterdir()] == ["known_0000.json"]
