"""The blind surface-code model (`models/surface.py`): a code along the object's x, read from a picture
alone, with no original mesh."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

import meshseal
from meshseal.cli import main
from meshseal.mesh import spherical_uv
from meshseal.models.surface import SurfaceCodeEncoder, read_picture, reference_columns, texel_columns

FIXTURES = Path(__file__).parent / "fixtures"


def test_texel_columns_trace_each_texel_to_the_surface_point_it_paints():
    sphere = trimesh.creation.icosphere(4)
    positions = torch.tensor(sphere.vertices, dtype=torch.float32)
    normals = torch.tensor(sphere.vertex_normals, dtype=torch.float32)
    faces = torch.tensor(sphere.faces)
    columns, painted = texel_columns(positions, normals, faces, spherical_uv(positions), 64, 64)
    # Spherical UVs: texel (row, col) paints the point of the unit sphere at its longitude and latitude.
    v = 1.0 - (torch.arange(64) + 0.5) / 64
    u = (torch.arange(64) + 0.5) / 64
    latitude, longitude = ((v - 0.5) * math.pi)[:, None], ((u - 0.5) * 2 * math.pi)[None, :]
    points = torch.stack([torch.cos(latitude) * torch.cos(longitude), torch.cos(latitude) * torch.sin(longitude),
                          torch.sin(latitude).expand(64, 64)], -1)
    expected = reference_columns(points, positions)
    assert painted.float().mean() > 0.9
    error = (columns - expected)[painted].abs()
    assert float(error.median()) < 0.01 and float(error.quantile(0.9)) < 0.03
    # and the column grows with x: the left of the object (x < 0) is the left of the picture
    assert float(columns[32, 32]) > 0.9 and float(columns[32, 1]) < 0.1


def test_the_mark_follows_the_column_code_at_the_texture_psnr():
    encoder = SurfaceCodeEncoder(8, cells=32, texture_psnr=30.0, floor=3.0)
    texture = torch.rand(1, 3, 64, 64)
    columns = torch.linspace(0, 1, 64).expand(64, 64)[None]
    painted = torch.ones(1, 64, 64, dtype=torch.bool)
    message = torch.tensor([[1.0, 0, 1, 1, 0, 0, 1, 0]])
    marked = encoder(torch.full_like(texture, 0.5), message, columns, painted)
    residual = marked - 0.5
    assert abs(float(-10 * torch.log10(residual.pow(2).mean())) - 30.0) < 0.1
    # a flat texture carries the code itself, in the mark's colour, constant down each column
    profile = (residual * encoder.colour[None, :, None, None]).sum(1)[0]
    assert torch.allclose(profile, profile[:1].expand_as(profile), atol=1e-6)
    code = torch.einsum("bk,kc->bc", 2 * message - 1, encoder.codes)[0]
    cells = profile[0].reshape(32, 2).mean(1)
    assert torch.equal(torch.sign(cells), torch.sign(code))
    # read back from the texture seen as a picture
    soft = read_picture(encoder, marked[0].permute(1, 2, 0).numpy(), np.ones((64, 64), dtype=bool))
    assert torch.equal((soft > 0).float(), message[0])


@pytest.mark.parametrize("model, bits, least", [("blind8", "10110010", 8), ("blind", "10110010011100101011001010100110", 29)])
def test_shipped_blind_models_read_pictures_without_the_mesh_or_metadata(tmp_path, capsys, model, bits, least):
    """embed -> render from the seed paper's views (600 x 400) -> saved without metadata -> detect, no --mesh."""
    assert main(["embed", str(FIXTURES / "bunny.glb"), "-o", str(tmp_path / "m.glb"), "--bits", bits, "--model", model]) == 0
    assert main(["render", str(tmp_path / "m.glb"), "-o", str(tmp_path / "v.png"), "--width", "600", "--height", "400",
                 "--views", "2", "--seed", "1"]) == 0
    assert main(["render", str(FIXTURES / "bunny.glb"), "-o", str(tmp_path / "o.png"), "--width", "600", "--height",
                 "400", "--views", "2", "--seed", "1"]) == 0
    pictures = []
    for name in ("v_0", "v_1", "o_0", "o_1"):  # pixels only, as a screenshot holds them
        path = tmp_path / f"{name}_plain.png"
        Image.open(tmp_path / f"{name}.png").convert("RGB").save(path)
        pictures.append(str(path))
    capsys.readouterr()
    assert main(["detect", *pictures, "--model", model, "--json"]) == 0
    results = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    agree = [sum(a == b for a, b in zip(r["bits"], bits)) for r in results]
    assert min(agree[:2]) >= least, agree
    if len(bits) >= 32:  # the unmarked bunny's pictures agree at chance (25 of 32 or more: p < 0.002)
        assert max(agree[2:]) < 25, agree
    assert all(r["p_value"] is None and r["detected"] is None for r in results)  # raw bits, no decision


def test_blind_models_are_listed_blind_and_need_no_mesh():
    listed = {m["name"]: m for m in meshseal.shipped_models()}
    for name, n_bits in (("blind", 32), ("blind8", 8)):
        assert listed[name]["informed"] is False and listed[name]["n_bits"] == n_bits
    watermarker = meshseal.load("blind8")
    assert not watermarker.informed
    with pytest.raises(meshseal.MeshsealError):
        watermarker.embed(meshseal.load_mesh(FIXTURES / "cube.off"), bits="10110010")  # no texture to carry it
