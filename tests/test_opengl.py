"""The real-OpenGL renderer against a numpy evaluation of docs/conventions.md."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from meshseal.mesh import Material, Mesh
from meshseal.render.cameras import Cameras
from meshseal.render.lighting import ATTENUATION, K_AMBIENT, K_DIFFUSE, PointLights, lights_at
from meshseal.render.opengl import OpenGLRenderer

pytest.importorskip("moderngl", reason="moderngl is not installed (pip install meshseal[gl])")


@pytest.fixture(scope="module")
def renderer(gl_renderer):
    return gl_renderer


def quad(x0=-1.0, x1=1.0, y0=-1.0, y1=1.0, z=0.0):
    """A quad in the plane z with uv (0, 0) at (x0, y0) and (1, 1) at (x1, y1), normal +z."""
    positions = torch.tensor([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=torch.float32)
    normals = torch.tensor([[0.0, 0.0, 1.0]] * 4)
    uvs = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    return positions, normals, uvs, faces


def cameras(eyes, up=(0.0, 1.0, 0.0), at=(0.0, 0.0, 0.0), fov_y=60.0):
    eye = torch.tensor(eyes, dtype=torch.float32).reshape(-1, 3)
    n = eye.shape[0]
    return Cameras(eye, torch.tensor([at] * n, dtype=torch.float32), torch.tensor([up] * n, dtype=torch.float32),
                   fov_y)


def bilinear_repeat(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear lookup, REPEAT wrap, texel centres at (k + 0.5) / size, uv (0, 0) = bottom-left."""
    h, w, _ = image.shape
    x = u * w - 0.5
    y = (1.0 - v) * h - 0.5  # image row coordinate, row 0 = top
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    x0, y0 = x0.astype(int), y0.astype(int)

    def at(r, c):
        return image[np.mod(r, h), np.mod(c, w)]

    return ((1 - fx) * (1 - fy) * at(y0, x0) + fx * (1 - fy) * at(y0, x0 + 1)
            + (1 - fx) * fy * at(y0 + 1, x0) + fx * fy * at(y0 + 1, x0 + 1))


def reference_plane(camera: Cameras, lights: PointLights, width, height, image, material, kr=0.0,
                    plane=(-1.0, 1.0, -1.0, 1.0)):
    """Conventions' Phong at every pixel centre for the quad `plane` in z = 0 (normal +z)."""
    x0, x1, y0, y1 = plane
    matrix = (camera.projection_matrix(width / height) @ camera.view_matrix())[0].double().numpy()
    inverse = np.linalg.inv(matrix)
    cols, rows = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    ndc_x = cols / width * 2 - 1
    ndc_y = 1 - rows / height * 2

    def unproject(z):
        clip = np.stack([ndc_x, ndc_y, np.full_like(ndc_x, z), np.ones_like(ndc_x)], -1) @ inverse.T
        return clip[..., :3] / clip[..., 3:]

    a, b = unproject(-1.0), unproject(1.0)
    t = -a[..., 2] / (b[..., 2] - a[..., 2])
    p = a + t[..., None] * (b - a)
    u = (p[..., 0] - x0) / (x1 - x0)
    v = (p[..., 1] - y0) / (y1 - y0)
    inside = (u >= 0) & (u <= 1) & (v >= 0) & (v <= 1)

    albedo = bilinear_repeat(image.astype(np.float64), u, v) * material["diffuse"]
    eye = camera.eye[0].double().numpy()
    n = np.array([0.0, 0.0, 1.0]) * np.where(np.sum((eye - p) * [0, 0, 1], -1, keepdims=True) < 0, -1, 1)
    view = eye - p
    view /= np.linalg.norm(view, axis=-1, keepdims=True)
    color = K_AMBIENT * material["ambient"] * albedo
    kc, kl, kq = ATTENUATION
    for position, intensity in zip(lights.position[0].double().numpy(), lights.intensity[0].double().numpy()):
        to_light = position - p
        d = np.linalg.norm(to_light, axis=-1, keepdims=True)
        l = to_light / d
        att = kc + kl * d + kq * d * d
        nl = np.sum(n * l, -1, keepdims=True)
        r = 2 * nl * n - l
        rv = np.maximum(np.sum(r * view, -1, keepdims=True), 0.0)
        color = color + intensity / att * (K_DIFFUSE * np.maximum(nl, 0) * albedo
                                           + kr * material["specular"] * rv ** material["shininess"])
    return np.clip(color, 0, 1), u, v, inside


def psnr(a, b):
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else 10 * math.log10(1.0 / mse)


@pytest.mark.parametrize("kr", [0.0, 0.6])
def test_textured_quad_matches_numpy_phong(renderer, kr):
    generator = torch.Generator().manual_seed(0)
    image = torch.rand(24, 32, 3, generator=generator)
    positions, normals, uvs, faces = quad()
    material = dict(ambient=np.array([0.3, 0.25, 0.2]), diffuse=np.array([0.9, 1.0, 0.8]),
                    specular=np.array([0.5, 0.6, 0.7]), shininess=12.0)
    mesh = Mesh(positions=positions, normals=normals, faces=faces, uvs=uvs,
                materials=[Material(texture=image, ambient=torch.tensor(material["ambient"]).float(),
                                    diffuse=torch.tensor(material["diffuse"]).float(),
                                    specular=torch.tensor(material["specular"]).float(),
                                    shininess=material["shininess"])])
    camera = cameras([[0.5, -0.7, 2.2]], up=(0.0, 1.0, 0.0), at=(0.1, 0.05, 0.0))
    lights = PointLights(torch.tensor([[[0.8, 0.6, 1.5], [-1.5, 0.5, 2.0]]]),
                         torch.tensor([[[1.0, 0.9, 0.8], [0.4, 0.5, 0.6]]]))
    width, height = 96, 72
    renderer.kr = kr  # the Phong constants are plain attributes, read at each render
    try:
        out = renderer.render(mesh, camera, lights, width, height)[0].numpy()
    finally:
        renderer.kr = 0.0
    expected, u, v, inside = reference_plane(camera, lights, width, height, image.numpy(), material, kr=kr)

    interior = (u > 0.02) & (u < 0.98) & (v > 0.02) & (v < 0.98)
    assert interior.sum() > 0.3 * width * height
    value = psnr(out[interior][:, :3], expected[interior])
    print(f"PSNR vs numpy Phong (kr={kr}): {value:.1f} dB")
    assert value > 40.0
    assert np.all(out[interior][:, 3] == 1.0)
    outside = ~((u > -0.02) & (u < 1.02) & (v > -0.02) & (v < 1.02))
    assert outside.sum() > 100
    assert np.all(out[outside] == 0.0)
    if kr > 0:  # the specular term is actually visible
        no_spec, *_ = reference_plane(camera, lights, width, height, image.numpy(), material, kr=0.0)
        assert np.abs(no_spec - expected)[interior].max() > 0.05


def test_orientation_row0_top_uv_bottom_left(renderer):
    image = torch.zeros(8, 8, 3)
    image[:, :, 2] = 1.0  # blue everywhere
    image[:4, :4] = torch.tensor([1.0, 0.0, 0.0])  # red top-left quarter of the image
    positions, normals, uvs, faces = quad()
    mesh = Mesh(positions=positions, normals=normals, faces=faces, uvs=uvs, materials=[Material(texture=image)])
    out = renderer.render(mesh, cameras([[0.0, 0.0, 2.5]]), lights_at(torch.tensor([[0.0, 0.0, 2.0]])), 64, 64)[0]
    # The quad spans about [11, 53] in both axes; probe the centres of its four quarters.
    top_left, top_right = out[22, 22, :3], out[22, 42, :3]
    bottom_left, bottom_right = out[42, 22, :3], out[42, 42, :3]
    assert top_left[0] > 0.3 and top_left[2] == 0.0
    for pixel in (top_right, bottom_left, bottom_right):
        assert pixel[2] > 0.3 and pixel[0] == 0.0


def test_background_and_alpha(renderer):
    positions, normals, uvs, faces = quad(-0.5, 0.5, -0.5, 0.5)
    mesh = Mesh(positions=positions, normals=normals, faces=faces, uvs=None)
    lights = lights_at(torch.tensor([[0.0, 0.0, 3.0]] * 2))
    out = renderer.render(mesh, cameras([[0.0, 0.0, 3.0], [0.0, 0.0, 4.0]]), lights, 40, 30,
                          background=(0.2, 0.4, 0.6))
    assert out.shape == (2, 30, 40, 4) and out.dtype == torch.float32
    for b in range(2):
        assert torch.equal(out[b, 0, 0], torch.tensor([0.2, 0.4, 0.6, 0.0]))
        assert out[b, 15, 20, 3] == 1.0 and out[b, 15, 20, :3].min() > 0.3  # white albedo
    assert (out[0, ..., 3] > 0).sum() > (out[1, ..., 3] > 0).sum()  # the farther camera sees a smaller quad
    assert set(out[..., 3].unique().tolist()) == {0.0, 1.0}


def test_multi_material(renderer):
    left = quad(-1.0, 0.0, -0.5, 0.5)
    right = quad(0.0, 1.0, -0.5, 0.5)
    red = torch.zeros(4, 4, 3)
    red[..., 0] = 1.0
    mesh = Mesh(positions=torch.cat([left[0], right[0]]), normals=torch.cat([left[1], right[1]]),
                uvs=torch.cat([left[2], right[2]]), faces=torch.cat([left[3], right[3] + 4]),
                face_material=torch.tensor([0, 0, 1, 1]),
                materials=[Material(texture=red), Material(texture=None, diffuse=torch.tensor([0.0, 1.0, 0.0]))])
    out = renderer.render(mesh, cameras([[0.0, 0.0, 2.5]]), lights_at(torch.tensor([[0.0, 0.0, 2.0]])), 64, 48)[0]
    left_pixel, right_pixel = out[24, 20], out[24, 44]
    assert left_pixel[0] > 0.3 and left_pixel[1] == 0.0 and left_pixel[3] == 1.0
    assert right_pixel[1] > 0.3 and right_pixel[0] == 0.0 and right_pixel[3] == 1.0


def test_render_batch_matches_render(renderer):
    positions, normals, uvs, faces = quad()
    generator = torch.Generator().manual_seed(1)
    textures = torch.rand(3, 3, 16, 16, generator=generator)
    shifts = torch.tensor([[0.0, 0.0, 0.0], [0.3, -0.2, 0.0], [-0.1, 0.2, 0.4]])
    batch_positions = positions.unsqueeze(0) + shifts.unsqueeze(1)
    cams = cameras([[0.0, -0.5, 3.0], [0.4, 0.2, 2.5], [-0.3, 0.0, 3.5]])
    lights = lights_at(torch.tensor([[1.0, 1.0, 2.0], [0.0, 0.5, 2.0], [-1.0, 0.0, 3.0]]))
    out = renderer.render_batch(batch_positions, normals, uvs, faces, textures, cams, lights, 48, 40)
    assert out.shape == (3, 40, 48, 4)
    for b in range(3):
        mesh = Mesh(positions=batch_positions[b], normals=normals, faces=faces, uvs=uvs,
                    materials=[Material(texture=textures[b].permute(1, 2, 0))])
        single = renderer.render(mesh, cams[b], lights[b], 48, 40)[0]
        assert torch.allclose(out[b], single, atol=1e-4)  # tile offset: float rounding only
        assert torch.equal(out[b, ..., 3], single[..., 3])
        assert single[..., 3].sum() > 100


def test_triangles_behind_near_are_dropped(renderer):
    positions = torch.tensor([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 2.95]])  # w = 0.05 < near
    normals = torch.tensor([[0.0, 0.0, 1.0]] * 3)
    faces = torch.tensor([[0, 1, 2]])
    lights = lights_at(torch.tensor([[0.0, 0.0, 2.0]]))
    drawn = Mesh(positions=positions * torch.tensor([1.0, 1.0, 0.9]), normals=normals, faces=faces)  # w = 0.345
    out = renderer.render(drawn, cameras([[0.0, 0.0, 3.0]]), lights, 32, 32)
    assert out[..., 3].max() == 1.0
    dropped = Mesh(positions=positions, normals=normals, faces=faces)
    out = renderer.render(dropped, cameras([[0.0, 0.0, 3.0]]), lights, 32, 32)  # same framebuffer: cleared
    assert out.abs().max() == 0.0


def test_chunked_tiles_match(renderer, monkeypatch):
    import meshseal.render.opengl as opengl

    positions, normals, uvs, faces = quad()
    textures = torch.rand(3, 3, 8, 8, generator=torch.Generator().manual_seed(2))
    cams = cameras([[0.0, 0.0, 3.0], [0.5, 0.0, 2.5], [0.0, -0.5, 3.5]])
    lights = lights_at(torch.tensor([[0.0, 1.0, 2.0]] * 3))
    whole = renderer.render_batch(positions, normals, uvs, faces, textures, cams, lights, 24, 20)
    monkeypatch.setattr(opengl, "_MAX_TILE_PIXELS", 2 * 24 * 20)  # two tiles per framebuffer
    chunked = renderer.render_batch(positions, normals, uvs, faces, textures, cams, lights, 24, 20)
    assert torch.allclose(whole, chunked, atol=1e-4) and whole[..., 3].sum() > 50


def test_no_context_is_one_clear_error():
    broken = OpenGLRenderer(backend="no-such-backend")
    with pytest.raises(RuntimeError, match="OpenGL renderer unavailable") as error:
        broken.render(None, cameras([[0.0, 0.0, 3.0]]), lights_at(torch.zeros(1, 3)), 8, 8)
    assert "\n" not in str(error.value)
