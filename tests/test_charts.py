"""Palette faces (UVs meeting at a point) get charts of their own (`methods.charts`), so that a spread mark
lies on them too: the charted mesh renders as the original, charting is deterministic, meshes that need
none are left alone, and the mark on a palette mesh survives a file round trip through the CLI."""

import json
import math

import numpy as np
import pytest
import torch
import trimesh

import meshseal
from meshseal.cli import main
from meshseal.mesh import Material, Mesh, normalize, save, to_z_up
from meshseal.methods.charts import chart_palette_faces, palette_surface_share
from meshseal.render import MeshBatch, MeshRenderer, sample_any_lights, sample_any_view_cameras

SWATCHES = ((0.8, 0.2, 0.1), (0.1, 0.5, 0.8), (0.9, 0.9, 0.3))


def palette_sphere() -> Mesh:
    """A sphere whose upper half is UV-mapped onto a noise texture (left half of a 32 x 32 texture) and
    whose lower half uses three flat swatches on its right half as a palette (every corner of a face on
    one swatch's centre), one vertex per face corner."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    corners = torch.from_numpy(np.asarray(sphere.vertices)[np.asarray(sphere.faces)]).float()  # (F, 3, 3)
    n_faces = len(corners)
    positions = corners.reshape(-1, 3)
    faces = torch.arange(3 * n_faces).reshape(n_faces, 3)
    texture = torch.zeros(32, 32, 3)
    texture[:, :16] = torch.rand(32, 16, 3, generator=torch.Generator().manual_seed(0)) * 0.6 + 0.2
    for index, colour in enumerate(SWATCHES):
        texture[index * 10: index * 10 + 10, 16:] = torch.tensor(colour)
    longitude = torch.atan2(positions[:, 1], positions[:, 0]) / (2 * math.pi) + 0.5
    uvs = torch.stack([(longitude * 0.5).clamp(0.01, 0.49), 0.02 + 0.96 * (positions[:, 2] + 1) / 2], 1)
    centroid = corners.mean(1)
    lower = centroid[:, 2] < 0
    swatch = ((torch.atan2(centroid[:, 1], centroid[:, 0]) + math.pi) / (2 * math.pi) * 3).long().clamp(0, 2)
    point = torch.stack([torch.full((n_faces,), 0.75), 1 - (swatch * 10 + 5) / 32], 1)  # swatch centres
    per_corner = point.repeat_interleave(3, 0)
    uvs = torch.where(lower.repeat_interleave(3)[:, None], per_corner, uvs)
    return Mesh(positions, torch.nn.functional.normalize(positions, dim=1), faces, uvs,
                materials=[Material(texture=texture)])


def _render(mesh: Mesh, views: int = 2) -> torch.Tensor:
    generator = torch.Generator().manual_seed(5)
    cameras, lights = sample_any_view_cameras(views, generator), sample_any_lights(views, generator)
    with torch.no_grad():
        return MeshRenderer()(MeshBatch.from_mesh(normalize(to_z_up(mesh))), cameras, lights, 128, 128).image


def test_charted_mesh_renders_as_the_original():
    mesh = palette_sphere()
    assert 0.4 < palette_surface_share(mesh) < 0.6
    charted = chart_palette_faces(mesh)
    assert charted.n_vertices > mesh.n_vertices and charted.n_faces == mesh.n_faces
    height, width = charted.materials[0].texture.shape[:2]
    assert height > 32 and torch.equal(charted.materials[0].texture[:32, :32], mesh.materials[0].texture)
    assert palette_surface_share(charted) == 0.0  # every palette face now has UV area ...
    assert chart_palette_faces(charted) is charted  # ... so charting again changes nothing
    assert float((_render(charted) - _render(mesh)).abs().max()) < 1e-4


def test_charting_is_deterministic_and_leaves_other_meshes_alone(tmp_path):
    first, second = chart_palette_faces(palette_sphere()), chart_palette_faces(palette_sphere())
    for a, b in ((first.uvs, second.uvs), (first.faces, second.faces),
                 (first.materials[0].texture, second.materials[0].texture)):
        assert torch.equal(a, b)
    bunny = meshseal.load_mesh("tests/fixtures/bunny.glb")  # UV-mapped: nothing to chart
    assert chart_palette_faces(bunny) is bunny
    tiled = palette_sphere()
    upper = tiled.uvs[:, 0] < 0.5
    tiled.uvs[upper] = tiled.uvs[upper] * 2.0  # a texture tiled twice over: moving it would break the tiling
    assert chart_palette_faces(tiled) is tiled


@pytest.mark.parametrize("suffix", ["glb", "obj"])
def test_palette_faces_carry_the_mark_through_files(tmp_path, capsys, suffix):
    original = tmp_path / f"palette.{suffix}"
    save(palette_sphere(), original)
    marked, picture = tmp_path / f"marked.{suffix}", tmp_path / "view.png"
    capsys.readouterr()
    assert main(["embed", str(original), "-o", str(marked), "--message", "ab42", "--views", "1", "--json"]) == 0
    captured = capsys.readouterr()
    assert "got charts of their own" in captured.err
    report = json.loads(captured.out)
    assert report["psnr_object"] > 40 and report["flip_object"] < 0.04
    loaded, before = meshseal.load_mesh(marked), meshseal.load_mesh(original)
    assert loaded.materials[0].texture.shape[0] > before.materials[0].texture.shape[0]
    in_memory = meshseal.load().embed(before, "ab42")  # what was written, before the file round trip
    assert float((_render(loaded) - _render(in_memory)).abs().max()) < 2 / 255  # 8-bit texels
    assert main(["render", str(marked), "-o", str(picture), "--width", "256", "--height", "256", "--seed", "2"]) == 0
    capsys.readouterr()
    assert main(["detect", str(picture), "--mesh", str(original), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["detected"] and result["message"] == "ab42"


def test_instances_of_one_geometry_are_charted_alike_and_written_once(tmp_path):
    """A glTF whose two nodes show one geometry: both instances get the same charts, so the file (which
    holds the geometry once) renders as the charted mesh in memory, and the mark reads from it."""
    import trimesh
    from PIL import Image

    mesh = palette_sphere()
    image = Image.fromarray((mesh.materials[0].texture.numpy() * 255).round().astype(np.uint8))
    visual = trimesh.visual.TextureVisuals(uv=mesh.uvs.numpy(), material=trimesh.visual.material.SimpleMaterial(image=image))
    geometry = trimesh.Trimesh(vertices=mesh.positions.numpy(), faces=mesh.faces.numpy(),
                               vertex_normals=mesh.normals.numpy(), visual=visual, process=False)
    scene = trimesh.Scene()
    scene.add_geometry(geometry, node_name="a", geom_name="sphere")
    moved = np.eye(4)
    moved[0, 3] = 2.5
    scene.graph.update(frame_to="b", frame_from=scene.graph.base_frame, geometry="sphere", matrix=moved)
    scene.export(tmp_path / "two.glb")
    original = meshseal.load_mesh(tmp_path / "two.glb")
    assert [p.geometry for p in original.source.parts] == ["sphere", "sphere"]
    marked = meshseal.load().embed(original, "ab42")
    first, second = marked.source.parts
    assert first.vertices.stop - first.vertices.start == second.vertices.stop - second.vertices.start
    assert torch.equal(marked.uvs[first.vertices], marked.uvs[second.vertices])
    save(marked, tmp_path / "marked.glb")
    reloaded = meshseal.load_mesh(tmp_path / "marked.glb")
    assert float((_render(reloaded) - _render(marked)).abs().max()) < 2 / 255
    picture = _render(reloaded, views=1)[0]
    generator = torch.Generator().manual_seed(5)
    cameras = sample_any_view_cameras(1, generator)
    wm = meshseal.load()
    result = wm.decide([wm.read(picture.permute(1, 2, 0).numpy(), wm.original(original), camera=cameras)])
    assert result.detected and result.message == "ab42"
