"""Each pixel's mean colour over a rasterization `scale` times finer, in one compiled pass.

`box_mean_render` gives what `rasterize` at (scale H, scale W), `MeshRenderer.shade` of every fragment
and a sum of each pixel's scale^2 sub-pixels give (informed reading's `picture_footprint`), without
forming the fragments: on the CPU the finer rasterization has 16 times the picture's fragments, and
gathering, interpolating and shading them one tensor operation at a time was most of a camera-known
reading. The arithmetic is the torch path's, in float32, fragment by fragment (screen and perspective
barycentrics as `rasterize`, `interpolate`, the bilinear REPEAT lookup of `sample_texture`, the Phong
terms of `PhongShader`); the sums agree with it to float rounding (tests/test_render.py).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ..versions import version
from .compiled import njit
from .lighting import ATTENUATION, K_AMBIENT, K_DIFFUSE
from .rasterizer import visible_faces_within, whole_raster


@njit(cache=True)
def _box_sums(pix_to_face, first_row, first_col, width, clip, faces, positions, normals, uvs, has_uv, face_material, texels,
              texel_offset, texel_height, texel_width, textured, diffuse, ambient, eye, light_position,
              light_intensity, half, scale, k_ambient, k_diffuse, attenuation, sums):  # pragma: no cover - compiled
    """pix_to_face: the window of the finer raster from (first_row, first_col) on; width: the picture's."""
    window_height, window_width = pix_to_face.shape
    one = np.float32(1.0)
    zero = np.float32(0.0)
    eps = np.float32(1e-12)
    screen_x = np.empty(clip.shape[0], np.float32)  # `clip_to_screen` of each vertex, once
    screen_y = np.empty(clip.shape[0], np.float32)
    for v in range(clip.shape[0]):
        screen_x[v] = half[0] + (clip[v, 0] / clip[v, 3]) * half[0]
        screen_y[v] = half[1] + (clip[v, 1] / clip[v, 3]) * (-half[1])
    for window_row in range(window_height):
        row = first_row + window_row
        py = np.float32(row) + np.float32(0.5)
        for window_col in range(window_width):
            f = pix_to_face[window_row, window_col]
            if f < 0:
                continue
            col = first_col + window_col
            px = np.float32(col) + np.float32(0.5)
            i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
            w0, w1, w2 = clip[i0, 3], clip[i1, 3], clip[i2, 3]
            dx0, dx1, dx2 = screen_x[i0] - px, screen_x[i1] - px, screen_x[i2] - px
            dy0, dy1, dy2 = screen_y[i0] - py, screen_y[i1] - py, screen_y[i2] - py
            s0 = dx1 * dy2 - dx2 * dy1
            s1 = dx2 * dy0 - dx0 * dy2
            s2 = dx0 * dy1 - dx1 * dy0
            total = s0 + s1 + s2
            p0 = (s0 / total) / w0
            p1 = (s1 / total) / w1
            p2 = (s2 / total) / w2
            norm = p0 + p1 + p2
            b0, b1, b2 = p0 / norm, p1 / norm, p2 / norm
            m = face_material[f]
            # the interpolated surface point, normal and albedo
            wx = positions[i0, 0] * b0 + positions[i1, 0] * b1 + positions[i2, 0] * b2
            wy = positions[i0, 1] * b0 + positions[i1, 1] * b1 + positions[i2, 1] * b2
            wz = positions[i0, 2] * b0 + positions[i1, 2] * b1 + positions[i2, 2] * b2
            nx = normals[i0, 0] * b0 + normals[i1, 0] * b1 + normals[i2, 0] * b2
            ny = normals[i0, 1] * b0 + normals[i1, 1] * b1 + normals[i2, 1] * b2
            nz = normals[i0, 2] * b0 + normals[i1, 2] * b1 + normals[i2, 2] * b2
            ar, ag, ab = one, one, one
            if has_uv and textured[m]:
                u = uvs[i0, 0] * b0 + uvs[i1, 0] * b1 + uvs[i2, 0] * b2
                t = uvs[i0, 1] * b0 + uvs[i1, 1] * b1 + uvs[i2, 1] * b2
                u = u - np.float32(np.floor(u))
                t = t - np.float32(np.floor(t))
                th, tw = texel_height[m], texel_width[m]
                x = u * np.float32(tw) + np.float32(0.5)
                y = (one - t) * np.float32(th) + np.float32(0.5)
                x0 = np.float32(np.floor(x))
                y0 = np.float32(np.floor(y))
                fx, fy = x - x0, y - y0
                c0 = min(max(int(x0), 0), tw)
                r0 = min(max(int(y0), 0), th)
                stride = tw + 2
                base = texel_offset[m] + r0 * stride + c0
                for k in range(3):
                    top = texels[base, k] + fx * (texels[base + 1, k] - texels[base, k])
                    bottom = texels[base + stride, k] + fx * (texels[base + stride + 1, k] - texels[base + stride, k])
                    value = top * (one - fy) + bottom * fy
                    if k == 0:
                        ar = value
                    elif k == 1:
                        ag = value
                    else:
                        ab = value
            ar, ag, ab = ar * diffuse[m, 0], ag * diffuse[m, 1], ab * diffuse[m, 2]
            length = max(np.float32(np.sqrt(nx * nx + ny * ny + nz * nz)), eps)
            nx, ny, nz = nx / length, ny / length, nz / length
            if nx * (eye[0] - wx) + ny * (eye[1] - wy) + nz * (eye[2] - wz) < zero:
                nx, ny, nz = -nx, -ny, -nz
            lr, lg, lb = zero, zero, zero
            for light in range(light_position.shape[0]):
                lx = light_position[light, 0] - wx
                ly = light_position[light, 1] - wy
                lz = light_position[light, 2] - wz
                distance = max(np.float32(np.sqrt(lx * lx + ly * ly + lz * lz)), eps)
                n_dot_l = max(nx * (lx / distance) + ny * (ly / distance) + nz * (lz / distance), zero)
                falloff = attenuation[0] + attenuation[1] * distance + attenuation[2] * distance * distance
                lr += light_intensity[light, 0] / falloff * k_diffuse * n_dot_l
                lg += light_intensity[light, 1] / falloff * k_diffuse * n_dot_l
                lb += light_intensity[light, 2] / falloff * k_diffuse * n_dot_l
            red = k_ambient * ambient[m, 0] * ar + lr * ar
            green = k_ambient * ambient[m, 1] * ag + lg * ag
            blue = k_ambient * ambient[m, 2] * ab + lb * ab
            parent = (row // scale) * width + col // scale
            sums[parent, 0] += min(max(red, zero), one)
            sums[parent, 1] += min(max(green, zero), one)
            sums[parent, 2] += min(max(blue, zero), one)
            sums[parent, 3] += one


_PACKED: list = []  # (textures, their versions, packed): the last few, kept alive so their memory is not reused


def _signature(texture) -> tuple | None:
    if texture is None:
        return None
    return texture.data_ptr(), texture.shape, texture.stride(), texture.dtype, texture.device, version(texture)


def _packed_textures(textures) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Textures (a list of (3, H, W) or None) padded by one texel circularly, channels last, one after
    another: (N, 3) float32, with each one's offset, height, width and whether it is there. Packed once
    for the same unmodified textures (every picture of one original: a folder of them)."""
    signature = [_signature(t) for t in textures]
    for kept, kept_signature, packed in _PACKED:
        if len(kept) == len(signature) and kept_signature == signature:
            return packed
    packed = _pack(textures)
    _PACKED[:] = [(list(textures), signature, packed)] + _PACKED[:3]
    return packed


def _pack(textures) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    blocks, offsets, heights, widths, present, at = [], [], [], [], [], 0
    for texture in textures:
        if texture is None:
            offsets.append(0), heights.append(1), widths.append(1), present.append(False)
            continue
        padded = F.pad(texture.detach().float().unsqueeze(0), (1, 1, 1, 1), mode="circular")[0]
        blocks.append(padded.permute(1, 2, 0).reshape(-1, 3))
        offsets.append(at), heights.append(texture.shape[1]), widths.append(texture.shape[2]), present.append(True)
        at += blocks[-1].shape[0]
    texels = torch.cat(blocks).cpu().numpy() if blocks else np.zeros((1, 3), np.float32)
    return (np.ascontiguousarray(texels), np.array(offsets, np.int64), np.array(heights, np.int64),
            np.array(widths, np.int64), np.array(present, np.bool_))


def fused(mesh, shader) -> bool:
    """Whether `box_mean_render` can shade `mesh` with `shader` (else the torch path): on the CPU, a
    list of textures, no specular term (the seed's Phong constants)."""
    return (mesh.positions.device.type == "cpu" and not torch.is_tensor(mesh.textures)
            and shader.k_specular == 0.0 and shader.k_ambient == K_AMBIENT and shader.k_diffuse == K_DIFFUSE)


def box_mean_render(mesh, cameras, lights, height: int, width: int, scale: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Each pixel of B pictures (height x width) of `mesh` (a MeshBatch on the CPU, see `fused`) from
    `cameras` under point `lights`: the mean over its scale x scale sub-pixels of the lit colour, hard
    edges (sub-pixels off the object count as 0), and the share of them the object covers ->
    (B * H * W, 4), and the finer rasterization's face index (B, scale H, scale W) (-1: background)."""
    sums, window, corner = box_mean_window(mesh, cameras, lights, height, width, scale)
    return sums, whole_raster(window, corner, height * scale, width * scale)


def box_mean_window(mesh, cameras, lights, height: int, width: int,
                    scale: int) -> tuple[torch.Tensor, torch.Tensor, tuple[int, int]]:
    """`box_mean_render`, with the finer rasterization's face index over the window of it that the
    object can cover alone (`rasterizer.visible_faces_within`, whose `whole_raster` is the rest):
    (B * H * W, 4), the window (B, h, w) and its (top, left) corner in fine pixels."""
    n_images = len(cameras)
    dtype = torch.float32
    positions = mesh.positions.expand(n_images, -1, -1) if mesh.positions.shape[0] == 1 else mesh.positions
    clip = cameras.world_to_clip(positions, width / height)
    pix_to_face, (top, left) = visible_faces_within(clip, mesh.faces, height * scale, width * scale, align=scale)
    texels, offsets, heights, widths, present = _packed_textures(mesh.textures)
    array = lambda t: np.ascontiguousarray(t.detach().to("cpu", dtype).numpy())  # noqa: E731
    half = np.array([0.5 * width * scale, 0.5 * height * scale], np.float32)
    sums = np.zeros((n_images, height * width, 4), np.float32)
    per_image = lambda t, b: t[b] if t.shape[0] > 1 else t[0]  # noqa: E731
    faces = mesh.faces if mesh.faces.dim() == 3 else mesh.faces.unsqueeze(0)
    material = mesh.face_material if mesh.face_material.dim() == 2 else mesh.face_material.unsqueeze(0)
    has_uv = mesh.uvs is not None
    for b in range(n_images):
        _box_sums(pix_to_face[b].numpy(), top, left, width, array(clip[b]), np.ascontiguousarray(per_image(faces, b).cpu().numpy().astype(np.int64)),
                  array(per_image(mesh.positions, b)), array(per_image(mesh.normals, b)),
                  array(per_image(mesh.uvs, b)) if has_uv else np.zeros((1, 2), np.float32), has_uv,
                  np.ascontiguousarray(per_image(material, b).cpu().numpy().astype(np.int64)), texels, offsets, heights,
                  widths, present, array(mesh.diffuse), array(mesh.ambient), array(cameras.eye[b]),
                  array(lights.position[b]), array(lights.intensity[b]), half, scale, np.float32(K_AMBIENT),
                  np.float32(K_DIFFUSE), np.array(ATTENUATION, np.float32), sums[b])
    sums /= np.float32(scale * scale)
    return torch.from_numpy(sums.reshape(-1, 4)), pix_to_face, (top, left)
