"""The asset attacks of `meshseal eval --attacks` (meshseal.evaluation.asset_attacks): what each does to
a marked mesh before it is rendered."""

import numpy as np
import pytest
import torch

from meshseal.evaluation import asset_attacks
from meshseal.evaluation.attacks import ASSET_NAMES
from meshseal.mesh import Material, Mesh, vertex_normals


@pytest.fixture
def sheet():
    """A bumpy 21 x 21 sheet textured by its x, y with a smooth red-to-green 64 x 48 texture plus grain."""
    n = 21
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    positions = torch.tensor(np.stack([x.ravel(), y.ravel(), 0.05 * np.sin(5 * x.ravel())], 1), dtype=torch.float32)
    grid = np.arange(n * n).reshape(n, n)
    a, b, c, d = grid[:-1, :-1].ravel(), grid[:-1, 1:].ravel(), grid[1:, :-1].ravel(), grid[1:, 1:].ravel()
    faces = torch.tensor(np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]))
    rng = np.random.default_rng(0)
    ramp = np.linspace(0.2, 0.8, 64)[None, :].repeat(48, 0)
    texture = np.stack([ramp, 0.8 - ramp + 0.2, np.full_like(ramp, 0.1)], 2) + rng.normal(0, 0.02, (48, 64, 3))
    texture = torch.tensor(np.clip(texture, 0, 1), dtype=torch.float32)
    return Mesh(positions, vertex_normals(positions, faces), faces, positions[:, :2].clone(),
                materials=[Material(texture=texture)])


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(-10 * torch.log10(((a - b) ** 2).mean()))


def test_the_library_names_every_asset_attack():
    assert tuple(asset_attacks.ASSET_ATTACKS) == ASSET_NAMES


@pytest.mark.parametrize("name", ["texture_jpeg90", "texture_bc1", "texture_bc7"])
def test_texture_codecs_change_the_texture_a_little_and_keep_its_colours(name, sheet):
    before = sheet.materials[0].texture.clone()
    out = asset_attacks.apply(name, sheet, np.random.default_rng(0))
    after = out.materials[0].texture
    assert torch.equal(sheet.materials[0].texture, before)  # the input is not changed
    assert after.shape == before.shape and not torch.equal(after, before)
    assert 28 < _psnr(after, before) < 60, _psnr(after, before)
    # colour order kept (a codec that swapped red and blue would fail): red rises, green falls along x
    assert float(after[:, -8:, 0].mean() - after[:, :8, 0].mean()) > 0.4
    assert float(after[:, :8, 1].mean() - after[:, -8:, 1].mean()) > 0.4
    assert torch.equal(out.faces, sheet.faces) and torch.equal(out.uvs, sheet.uvs)


def test_block_compression_of_a_size_not_a_multiple_of_four(sheet):
    odd = Mesh(sheet.positions, sheet.normals, sheet.faces, sheet.uvs,
               materials=[Material(texture=sheet.materials[0].texture[:46, :63])])
    out = asset_attacks.apply("texture_bc7", odd, np.random.default_rng(0))
    assert out.materials[0].texture.shape == (46, 63, 3)
    assert _psnr(out.materials[0].texture, odd.materials[0].texture) > 30


def test_halved_texture(sheet):
    out = asset_attacks.apply("texture_half", sheet, np.random.default_rng(0))
    assert out.materials[0].texture.shape == (24, 32, 3)
    assert torch.equal(out.uvs, sheet.uvs)


def test_conversion_keeps_the_geometry_and_the_uvs(sheet):
    out = asset_attacks.apply("obj_glb", sheet, np.random.default_rng(0))
    assert out.n_faces == sheet.n_faces
    # the same surface points carry the same UVs (vertex order may change): match by position
    keys = {tuple(np.round(p, 4)): uv for p, uv in zip(sheet.positions.numpy(), sheet.uvs.numpy())}
    for point, uv in zip(out.positions.numpy(), out.uvs.numpy()):
        assert np.allclose(keys[tuple(np.round(point, 4))], uv, atol=1e-5)
    assert _psnr(out.materials[0].texture, sheet.materials[0].texture) > 50  # re-saved losslessly


def test_decimation_halves_the_faces_and_keeps_the_texture_on_the_surface(sheet):
    out = asset_attacks.apply("decimate0.5", sheet, np.random.default_rng(0))
    assert out.n_faces <= sheet.n_faces // 2
    assert float((out.uvs - out.positions[:, :2]).norm(dim=1).mean()) < 0.005
