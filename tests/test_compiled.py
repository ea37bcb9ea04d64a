"""The renderer's compiled kernels load when they pay (`render.compiled`): the torch paths a process takes
before that give the kernels' own bits, and a command that reads one camera-known picture never imports
numba."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from meshseal.mesh import load, normalize, to_z_up
from meshseal.render import MeshRenderer, sample_seed_cameras, sample_seed_lights
from meshseal.render import compiled, rasterizer, splatter

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "tests" / "fixtures"


@pytest.fixture
def torch_paths(monkeypatch):
    """Every job takes its torch path, as in a process that has not loaded the kernels."""
    compiled.load()
    monkeypatch.setattr(compiled, "spare", lambda size: True)


def kernel_and_torch(render, monkeypatch):
    compiled.load()
    with monkeypatch.context() as patch:
        patch.setattr(compiled, "spare", lambda size: False)
        kernel = render()
    with monkeypatch.context() as patch:
        patch.setattr(compiled, "spare", lambda size: True)
        calls = []
        for module, name in ((rasterizer, "_zbuffer_torch"), (splatter, "_forward_torch")):
            original = getattr(module, name)
            patch.setattr(module, name, lambda *a, _o=original, _n=name: calls.append(_n) or _o(*a))
        in_torch = render()
    return kernel, in_torch, calls


@pytest.mark.parametrize("name", ["bunny.glb", "suzanne.glb", "teapot/teapot.obj"])
@pytest.mark.parametrize("size,batch", [(256, 1), (96, 3)])
def test_torch_paths_render_the_kernels_bits(name, size, batch, monkeypatch):
    mesh = normalize(to_z_up(load(FIXTURES / name)))
    cameras = sample_seed_cameras(batch, torch.Generator().manual_seed(size))
    lights = sample_seed_lights(batch, torch.Generator().manual_seed(size))
    for blend in ("splat", "hard"):
        kernel, in_torch, calls = kernel_and_torch(
            lambda: MeshRenderer(blend=blend).render(mesh, cameras, lights, size, size), monkeypatch)
        assert "_zbuffer_torch" in calls and (blend == "hard" or "_forward_torch" in calls)
        assert torch.equal(kernel, in_torch)


def test_the_torch_zbuffer_in_runs_and_windows(monkeypatch):
    """The z-buffer's torch path tests its pairs in runs (PAIRS_AT_ONCE) and over a window of the raster
    (`visible_faces_within`): the kernel's faces and depths, ties to the first face included."""
    mesh = normalize(to_z_up(load(FIXTURES / "bunny.glb")))
    cameras = sample_seed_cameras(4, torch.Generator().manual_seed(3))
    clip = cameras.world_to_clip(mesh.positions.to(torch.float32)[None].expand(4, -1, -1), 1.0)
    monkeypatch.setattr(rasterizer, "PAIRS_AT_ONCE", 777)
    for align in (None, 8):
        kernel, in_torch, calls = kernel_and_torch(
            lambda: rasterizer._visible(clip, mesh.faces, 120, 100, 1e-5, align, True), monkeypatch)
        assert calls and kernel[1] == in_torch[1]
        assert torch.equal(kernel[0], in_torch[0]) and torch.equal(kernel[2], in_torch[2])
    # two coplanar copies of a face: the first drawn keeps every pixel, as in the kernel
    xy = np.array([[[10.0, 10.0], [50.0, 12.0], [20.0, 40.0], [10.0, 10.0], [50.0, 12.0], [20.0, 40.0]]])
    z, w = np.full((1, 6), 0.5), np.ones((1, 6))
    faces = np.array([[[3, 4, 5], [0, 1, 2]]])
    outs = []
    for zbuffer in (rasterizer._zbuffer, rasterizer._zbuffer_torch):
        face_out, depth = np.full((1, 64, 64), -1), np.full((1, 64, 64), np.inf)
        zbuffer(xy, z, w, faces, 1e-5, face_out, depth, 0, 0, 64, 64)
        outs.append(face_out)
    assert np.array_equal(outs[0], outs[1]) and set(np.unique(outs[0])) == {-1, 0}


def test_torch_paths_are_rented_until_they_cost_a_load(monkeypatch):
    monkeypatch.setattr(compiled, "_numba", None)
    monkeypatch.setattr(compiled, "_spent", 0.0)
    assert compiled.spare(1000) and not compiled.spare(compiled.SMALL_JOB + 1)
    monkeypatch.setattr(compiled, "_spent", compiled.LOAD_SECONDS)
    assert not compiled.spare(1000)


def test_a_command_with_several_pictures_loads_the_kernels_first(monkeypatch):
    """`for_pictures`: from PICTURES_TO_LOAD pictures on, the kernels load before the first reading
    (the rent rule would load them only after several slower ones); fewer keep the torch paths."""
    loads = []
    monkeypatch.setattr(compiled, "load", lambda: loads.append(1))
    compiled.for_pictures(compiled.PICTURES_TO_LOAD - 1)
    assert loads == []
    compiled.for_pictures(compiled.PICTURES_TO_LOAD)
    assert loads == [1]


PROBE = """
import json, sys
if sys.argv[3] == "kernels":
    from meshseal.render import compiled
    compiled.load()
sys.argv = ["meshseal", "detect", sys.argv[1], "--mesh", sys.argv[2], "--json"]
from meshseal.cli import main
try:
    main()
except SystemExit:
    pass
print(json.dumps({"numba": "numba" in sys.modules}))
"""


def test_one_camera_known_picture_is_read_without_numba(tmp_path):
    """`meshseal detect` of one picture that carries its camera never imports numba (its first call
    would cost more than the reading) and prints what the kernels would have given."""
    from meshseal.cli import main

    picture, mesh, marked = tmp_path / "bunny.png", str(FIXTURES / "bunny.glb"), str(tmp_path / "marked.glb")
    env = {**os.environ, "MESHSEAL_THREADS": "1"}
    # made in this process (only the reading must start afresh), marked at strength 1 without the budget's renders
    assert main(["embed", mesh, "-o", marked, "--message", "ab42", "--views", "0"]) == 0
    assert main(["render", marked, "-o", str(picture), "--width", "160", "--height", "160"]) == 0
    outputs = {}
    for how in ("torch", "kernels"):
        lines = subprocess.run([sys.executable, "-c", PROBE, str(picture), mesh, how], capture_output=True, text=True,
                               check=True, env=env).stdout.strip().splitlines()
        outputs[how] = [json.loads(line) for line in lines]
    assert outputs["torch"][-1] == {"numba": False} and outputs["kernels"][-1] == {"numba": True}
    assert outputs["torch"][0] == outputs["kernels"][0]
    assert outputs["torch"][0]["detected"] is True and outputs["torch"][0]["message"] == "ab42"
