"""The differentiable renderer: gradients (gradcheck in float64), conventions, samplers, batching."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from meshseal.mesh import Material, Mesh, load, normalize, to_z_up, vertex_normals
from meshseal.render import (Cameras, MeshBatch, MeshRenderer, cameras_from_eyes, clip_to_screen, lights_at,
                             sample_any_lights, sample_any_view_cameras, sample_seed_cameras,
                             sample_seed_lights, splat)

FIXTURES = Path(__file__).parent / "fixtures"
SIZE = 12


def pyramid(dtype=torch.float64) -> Mesh:
    """A square pyramid (apex up, +Z) with a random 4x4 texture: 4 side faces + 2 base faces."""
    generator = torch.Generator().manual_seed(0)
    positions = torch.tensor([[-0.8, -0.7, 0.0], [0.75, -0.8, 0.0], [0.8, 0.7, 0.05], [-0.7, 0.8, -0.05],
                              [0.05, -0.05, 0.9]], dtype=dtype)
    faces = torch.tensor([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4], [0, 2, 1], [0, 3, 2]])
    uvs = torch.tensor([[0.1, 0.1], [0.9, 0.15], [0.85, 0.9], [0.15, 0.85], [0.45, 0.55]], dtype=dtype)
    texture = 0.2 + 0.6 * torch.rand(4, 4, 3, generator=generator, dtype=dtype)
    material = Material(name="m", texture=texture, ambient=torch.full((3,), 0.25, dtype=dtype),
                        diffuse=torch.ones(3, dtype=dtype), specular=torch.zeros(3, dtype=dtype))
    return Mesh(positions, vertex_normals(positions, faces), faces, uvs=uvs, materials=[material])


def setup(dtype=torch.float64):
    cameras = cameras_from_eyes(torch.tensor([[0.3, -1.6, 2.0]], dtype=dtype))
    lights = lights_at(torch.tensor([[1.5, -1.0, 2.5]], dtype=dtype), intensity=0.6)
    return cameras, lights


def render_with(mesh: Mesh, blend: str, **override) -> torch.Tensor:
    """RGBA of the pyramid with some of positions / normals / uvs / texture replaced."""
    cameras, lights = setup(mesh.positions.dtype)
    batch = MeshBatch.from_mesh(mesh)
    if "texture" in override:
        batch.textures = [override["texture"].permute(2, 0, 1)]
    for key in ("positions", "normals", "uvs"):
        if key in override:
            setattr(batch, key, override[key].unsqueeze(0))
    return MeshRenderer(blend=blend)(batch, cameras, lights, SIZE, SIZE).rgba


def test_tiny_scene_is_in_view():
    rgba = render_with(pyramid(), "hard")
    coverage = rgba[0, ..., 3]
    assert 0.2 < float(coverage.mean()) < 0.9  # the silhouette is inside the image
    assert float(rgba[0, ..., :3].max()) < 1.0  # no clamping: smooth in every input


@pytest.mark.parametrize("blend", ["hard", "splat"])
@pytest.mark.parametrize("name", ["texture", "normals", "uvs"])
def test_gradcheck_attributes(blend, name):
    mesh = pyramid()
    value = {"texture": mesh.materials[0].texture, "normals": mesh.normals, "uvs": mesh.uvs}[name]
    value = value.clone().requires_grad_(True)
    # The splat path's full Jacobian is slow to build output by output: check random projections of it.
    assert torch.autograd.gradcheck(lambda x: render_with(mesh, blend, **{name: x}), (value,),
                                    eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=blend == "splat")


def test_gradcheck_positions_hard():
    mesh = pyramid()
    positions = mesh.positions.clone().requires_grad_(True)
    # Normals held fixed: gradients flow through projection, barycentrics, world position and lighting.
    assert torch.autograd.gradcheck(lambda x: render_with(mesh, "hard", positions=x), (positions,),
                                    eps=1e-7, atol=1e-5, rtol=1e-4)


def test_gradient_reaches_silhouette_vertices_through_splats():
    mesh = pyramid()
    weights = torch.rand(SIZE, SIZE, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    grads = {}
    for blend in ("hard", "splat"):
        positions = mesh.positions.clone().requires_grad_(True)
        coverage = render_with(mesh, blend, positions=positions)[0, ..., 3]
        if coverage.requires_grad:
            (coverage * weights).sum().backward()
        grads[blend] = positions.grad if positions.grad is not None else torch.zeros_like(positions)
    assert float(grads["hard"].abs().max()) == 0.0  # hard coverage is a step function
    # The base corners (0..3) form the silhouette seen from above: each gets a screen-space gradient.
    silhouette = grads["splat"][:4]
    assert torch.isfinite(silhouette).all()
    assert bool((silhouette.norm(dim=-1) > 1e-4).all())


def test_gradcheck_splat():
    generator = torch.Generator().manual_seed(2)
    n, h, w = 1, 5, 6
    rows = torch.arange(h, dtype=torch.float64).reshape(h, 1).expand(h, w) + 0.5
    cols = torch.arange(w, dtype=torch.float64).reshape(1, w).expand(h, w) + 0.5
    centres = torch.stack([cols, rows], dim=-1).unsqueeze(0)
    color = torch.rand(n, h, w, 3, generator=generator, dtype=torch.float64).requires_grad_(True)
    background = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    # Binary coverage (as the renderer makes): w.r.t. colours.
    mask = (torch.rand(n, h, w, generator=generator) > 0.4).to(torch.float64)
    assert torch.autograd.gradcheck(lambda c: splat(c, mask, centres, background), (color,), fast_mode=True)
    # Partial coverage (total weight < 1 everywhere, away from the normalisation's kink): w.r.t. colours
    # and splat positions, evaluated at the pixel centres.
    alpha = 0.05 + 0.4 * torch.rand(n, h, w, generator=generator, dtype=torch.float64)
    xy = centres.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda c, p: splat(c, alpha, p, background), (color, xy), fast_mode=True)


def test_splat_interior_is_exact():
    # A uniformly coloured region keeps its colour and full coverage away from its border;
    # background pixels next to it get partial coverage (antialiasing).
    color = torch.tensor([0.3, 0.6, 0.9]).expand(1, 8, 9, 3).clone()
    alpha = torch.zeros(1, 8, 9)
    alpha[:, 2:6, 2:7] = 1.0
    rows, cols = torch.meshgrid(torch.arange(8) + 0.5, torch.arange(9) + 0.5, indexing="ij")
    image, coverage = splat(color, alpha, torch.stack([cols, rows], -1).unsqueeze(0).float(), torch.zeros(3))
    assert torch.allclose(coverage[:, 3:5, 3:6], torch.ones(1, 2, 3))
    assert torch.allclose(image[:, 3:5, 3:6], color[:, 3:5, 3:6], atol=1e-6)
    assert 0.0 < float(coverage[0, 1, 4]) < 1.0 and float(coverage[0, 0, 0]) == 0.0


# ---------------------------------------------------------------- conventions


def project(cameras: Cameras, points, height: int, width: int) -> torch.Tensor:
    points = torch.as_tensor(points, dtype=torch.float32).reshape(1, -1, 3)
    return clip_to_screen(cameras.world_to_clip(points, width / height), height, width)[0]


def test_camera_conventions():
    cameras = cameras_from_eyes(torch.tensor([[0.0, -2.5, 3.0]]))  # the seed's camera, Z up
    height, width = 48, 64
    target, right, up = project(cameras, [[0, 0, 0], [0.5, 0, 0], [0, 0, 0.5]], height, width)
    assert torch.allclose(target, torch.tensor([width / 2, height / 2]), atol=1e-4)  # centre of the image
    assert right[0] > width / 2 + 1 and abs(float(right[1]) - height / 2) < 1e-3  # +x is to the right
    assert up[1] < height / 2 - 1 and abs(float(up[0]) - width / 2) < 1e-3  # +z is up (smaller rows)
    # Field of view: a point on the top edge of the 60 degree frustum lands on row 0.
    eye = torch.tensor([0.0, 0.0, 3.0])
    top = eye + torch.tensor([0.0, math.tan(math.radians(30.0)), -1.0])
    cameras = Cameras(eye.reshape(1, 3), torch.zeros(1, 3), torch.tensor([[0.0, 1.0, 0.0]]))
    assert torch.allclose(project(cameras, top, height, width)[0, 1], torch.tensor(0.0), atol=1e-4)


def test_rendered_image_is_upright_and_not_mirrored():
    # A quad facing the camera with uv (0, 0) at its bottom-left and a 2x2 texture:
    # image row 0 = [red, green], row 1 = [blue, white]  ->  red must appear top-left.
    positions = torch.tensor([[-1.0, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    uvs = torch.tensor([[0.0, 0], [1, 0], [1, 1], [0, 1]])
    texture = torch.tensor([[[1.0, 0, 0], [0, 1, 0]], [[0, 0, 1], [1, 1, 1]]])
    mesh = Mesh(positions, vertex_normals(positions, faces), faces, uvs=uvs,
                materials=[Material(texture=texture)])
    cameras = cameras_from_eyes(torch.tensor([[0.0, -3.0, 0.0]]))
    rgba = MeshRenderer(blend="hard").render(mesh, cameras, lights_at(torch.tensor([[0.0, -3.0, 0.0]])), 40, 40)
    image = rgba[0, ..., :3]
    centre = lambda r, c: image[r, c]  # noqa: E731
    top_left, top_right = centre(14, 14), centre(14, 25)
    bottom_left, bottom_right = centre(25, 14), centre(25, 25)
    assert top_left.argmax() == 0 and top_right.argmax() == 1 and bottom_left.argmax() == 2
    assert float(bottom_right.min()) > 0.5
    assert float(rgba[0, 0, 0, 3]) == 0.0 and float(rgba[0, 20, 20, 3]) == 1.0


def test_background_colour():
    mesh = pyramid(torch.float32)
    cameras, lights = setup(torch.float32)
    for blend in ("hard", "splat"):
        rgba = MeshRenderer(blend=blend).render(mesh, cameras, lights, SIZE, SIZE, background=(0.2, 0.4, 0.6))
        assert torch.allclose(rgba[0, 0, 0], torch.tensor([0.2, 0.4, 0.6, 0.0]))


# ---------------------------------------------------------------- samplers


def test_seed_samplers_are_seeded_and_in_range():
    a = sample_seed_cameras(64, torch.Generator().manual_seed(5))
    b = sample_seed_cameras(64, torch.Generator().manual_seed(5))
    c = sample_seed_cameras(64, torch.Generator().manual_seed(6))
    assert torch.equal(a.eye, b.eye) and not torch.equal(a.eye, c.eye)
    assert torch.all(a.eye[:, 0] == 0)
    assert torch.all((a.eye[:, 1] >= -3) & (a.eye[:, 1] <= -2))
    assert torch.all((a.eye[:, 2] >= 2) & (a.eye[:, 2] <= 4))
    assert torch.all(a.at == 0) and torch.all(a.up == torch.tensor([0.0, 0.0, 1.0]))
    assert a.fov_y == 60.0
    lights = sample_seed_lights(256, torch.Generator().manual_seed(5))
    assert torch.equal(lights.position, sample_seed_lights(256, torch.Generator().manual_seed(5)).position)
    assert torch.allclose(lights.position.mean(dim=(0, 1)), torch.tensor([2.0, 1.0, 2.0]), atol=0.06)


def test_any_view_samplers_are_seeded_and_in_range():
    a = sample_any_view_cameras(200, torch.Generator().manual_seed(7))
    b = sample_any_view_cameras(200, torch.Generator().manual_seed(7))
    assert torch.equal(a.eye, b.eye)
    radius = a.eye.norm(dim=-1)
    elevation = torch.rad2deg(torch.asin(a.eye[:, 2] / radius))
    assert torch.all((radius >= 2.8 - 1e-5) & (radius <= 5.0 + 1e-5))
    assert torch.all((elevation >= 10 - 1e-3) & (elevation <= 60 + 1e-3))
    azimuth = torch.atan2(a.eye[:, 1], a.eye[:, 0])
    assert float(azimuth.min()) < -2.5 and float(azimuth.max()) > 2.5  # all around
    lights = sample_any_lights(200, torch.Generator().manual_seed(7))
    assert torch.equal(lights.position, sample_any_lights(200, torch.Generator().manual_seed(7)).position)
    distance = lights.position.norm(dim=-1)
    assert torch.all((distance >= 2.0 - 1e-5) & (distance <= 4.0 + 1e-5))
    assert torch.all(lights.position[..., 2] > 0)


# ---------------------------------------------------------------- batching, devices, materials


def fixture_scene(name: str) -> Mesh:
    return normalize(to_z_up(load(FIXTURES / name)))


@pytest.mark.parametrize("blend", ["hard", "splat"])
def test_batched_equals_single(blend):
    mesh = fixture_scene("bunny.glb")
    cameras = sample_seed_cameras(3, torch.Generator().manual_seed(0))
    lights = sample_seed_lights(3, torch.Generator().manual_seed(0))
    renderer = MeshRenderer(blend=blend)
    together = renderer.render(mesh, cameras, lights, 40, 32)
    assert together.shape == (3, 32, 40, 4)
    for k in range(3):
        alone = renderer.render(mesh, cameras[k], lights[k], 40, 32)
        assert torch.allclose(together[k], alone[0], atol=1e-6)


def test_reshading_reuses_the_rasterization():
    """Passing a view's fragments back (re-lighting the same view) gives the same picture, with
    gradients to the shading inputs intact."""
    mesh = fixture_scene("bunny.glb")
    cameras = sample_seed_cameras(2, torch.Generator().manual_seed(1))
    lights = sample_seed_lights(2, torch.Generator().manual_seed(2))
    renderer, batch = MeshRenderer(), MeshBatch.from_mesh(mesh)
    first = renderer(batch, cameras, lights_at(cameras.eye, 0.3), 32, 40)
    batch.ambient = batch.ambient.clone().requires_grad_(True)
    again = renderer(batch, cameras, lights, 32, 40, fragments=first.fragments)
    fresh = renderer(batch, cameras, lights, 32, 40)
    assert torch.allclose(again.rgba, fresh.rgba, atol=1e-6)
    assert not torch.allclose(again.rgba, first.rgba, atol=1e-2)
    again.rgba.sum().backward()
    assert batch.ambient.grad.abs().sum() > 0


def test_batch_of_meshes_equals_single():
    base = fixture_scene("suzanne.glb")
    generator = torch.Generator().manual_seed(0)
    textures = torch.rand(2, 3, 16, 16, generator=generator)
    positions = torch.stack([base.positions, base.positions * 0.8])
    normals = torch.stack([base.normals, base.normals])
    uvs = torch.stack([base.uvs, base.uvs])
    cameras = sample_seed_cameras(2, generator)
    lights = sample_seed_lights(2, generator)
    renderer = MeshRenderer(blend="splat")
    together = renderer(MeshBatch.from_tensors(positions, normals, uvs, base.faces, textures),
                        cameras, lights, 32, 32).rgba
    for k in range(2):
        single = Mesh(positions[k], normals[k], base.faces, uvs=uvs[k],
                      materials=[Material(texture=textures[k].permute(1, 2, 0))])
        alone = renderer.render(single, cameras[k], lights[k], 32, 32)
        assert torch.allclose(together[k], alone[0], atol=1e-5)


def test_device_agnostic():
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    mesh = pyramid(torch.float32)
    cameras, lights = setup(torch.float32)
    reference = None
    for name in devices:
        device = torch.device(name)
        moved = mesh.to(device)
        assert moved.positions.device.type == device.type and moved.materials[0].texture.device.type == device.type
        texture = moved.materials[0].texture.clone().requires_grad_(True)
        batch = MeshBatch.from_mesh(moved)
        batch.textures = [texture.permute(2, 0, 1)]
        rgba = MeshRenderer()(batch, cameras.to(device), lights.to(device), SIZE, SIZE).rgba
        assert rgba.device.type == device.type
        rgba.sum().backward()
        assert texture.grad is not None and texture.grad.device.type == device.type
        reference = rgba.cpu() if reference is None else reference
        assert torch.allclose(rgba.cpu(), reference, atol=1e-4)


def test_multi_material_renders_every_texture():
    mesh = fixture_scene("multi_material.glb")
    cameras = cameras_from_eyes(torch.tensor([[0.0, -2.5, 1.5]]))
    lights = lights_at(torch.tensor([[0.0, -2.5, 2.0]]))
    renderer = MeshRenderer(blend="hard")
    output = renderer(MeshBatch.from_mesh(mesh), cameras, lights, 96, 96)
    visible = output.fragments.pix_to_face[0]
    material_at = torch.where(visible >= 0, mesh.face_material[visible.clamp_min(0)], -1)
    textured = [k for k, m in enumerate(mesh.materials) if m.texture is not None]
    assert len(textured) == 2
    for k in textured:
        pixels = material_at == k
        assert int(pixels.sum()) > 30, f"material {mesh.materials[k].name} not visible"
        # Blacking out this texture darkens exactly its own pixels.
        changed = mesh.copy()
        changed.materials[k].texture = torch.zeros_like(changed.materials[k].texture)
        rgba = renderer.render(changed, cameras, lights, 96, 96)
        difference = (rgba[0, ..., :3] - output.rgba[0, ..., :3]).abs().amax(-1) > 1e-6
        assert bool(difference[~pixels].any()) is False
        assert float(difference[pixels].float().mean()) > 0.9


def test_a_texture_stack_samples_as_the_list_does():
    """Training batches sample a (N, C, H, W) stack in one gather; values and gradients match the list path."""
    from meshseal.render.texture import sample_textures

    generator = torch.Generator().manual_seed(0)
    stack = torch.rand(5, 3, 16, 12, generator=generator, dtype=torch.float64)
    uv = torch.rand(3000, 2, generator=generator, dtype=torch.float64) * 3 - 1  # across the seams
    index = torch.randint(0, 5, (3000,), generator=generator)
    results = []
    for textures in (list(stack.clone().unbind(0)), stack.clone()):
        leaves = [t.requires_grad_() for t in textures] if isinstance(textures, list) else [textures.requires_grad_()]
        coords = uv.clone().requires_grad_()
        values = sample_textures(textures, coords, index)
        (values * torch.linspace(0, 1, values.numel(), dtype=values.dtype).reshape(values.shape)).sum().backward()
        results.append((values, torch.stack([t.grad for t in leaves]).reshape(5, 3, 16, 12), coords.grad))
    for a, b in zip(*results):
        assert torch.allclose(a, b, atol=1e-12)
