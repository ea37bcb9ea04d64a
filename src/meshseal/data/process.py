"""Turn a RawMesh into one fixed-size dataset item.

normalise to [-1, 1] in the Z-up frame -> weld -> simplify to at most `n_faces` (or subdivide small
meshes) -> per-corner UVs carried over from the original surface -> weld by (position, uv) ->
vertex normals -> pad to (Vmax, Fmax). Multi-material meshes get one texture: the materials are packed
into an N x N atlas (textured materials as cells, flat-colour materials as swatches of a palette cell).
A mesh without its own texture gets spherical UVs and a real or Gaussian-smoothed noise texture.

The geometry steps shared with the rest of the package (vertex normals, spherical UVs, quadric
decimation, the Y-up to Z-up rotation) are `meshseal.mesh`'s, applied to numpy arrays here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from PIL import Image
from scipy.ndimage import gaussian_filter
from scipy.spatial import cKDTree

from ..errors import MeshError
from ..mesh.preprocess import Y_UP_TO_Z_UP, decimate, spherical_uv, vertex_normals
from .formats import RawMesh, read_image

Y_TO_Z = np.array(Y_UP_TO_Z_UP)
MAX_CELLS = 16


@dataclass
class ProcessOptions:
    n_faces: int = 5000
    max_verts: int = 5000
    texture_size: int = 128
    p_noise: float = 0.5  # for meshes without their own texture: noise vs real texture image
    min_faces: int = 4


@dataclass
class Item:
    positions: np.ndarray  # (Vmax, 3) float32
    normals: np.ndarray
    uvs: np.ndarray  # (Vmax, 2)
    faces: np.ndarray  # (Fmax, 3) int32
    n_verts: int
    n_faces: int
    texture: np.ndarray  # (T, T, 3) uint8
    texture_kind: str  # own | real | noise
    texture_source: str


# ------------------------------------------------------------------ textures


def noise_texture(rng: np.random.Generator, size: int) -> np.ndarray:
    """The seed's noise texture: white noise smoothed by a Gaussian, stretched to [0, 255]."""
    sigma = float(rng.uniform(1.0, 6.0))
    noise = rng.random((size, size, 3))
    smooth = np.stack([gaussian_filter(noise[..., c], sigma, mode="wrap") for c in range(3)], axis=-1)
    low, high = smooth.min(axis=(0, 1)), smooth.max(axis=(0, 1))
    smooth = (smooth - low) / np.maximum(high - low, 1e-6)
    return (smooth * 255.0 + 0.5).astype(np.uint8)


def random_crop(image: np.ndarray, rng: np.random.Generator, size: int) -> np.ndarray:
    """A random square crop (at least half the image side), resized to size x size, maybe flipped."""
    h, w = image.shape[:2]
    side = int(rng.integers(max(1, min(h, w) // 2), min(h, w) + 1))
    top, left = int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))
    crop = image[top:top + side, left:left + side]
    if rng.random() < 0.5:
        crop = crop[:, ::-1]
    return resize(np.ascontiguousarray(crop), size, size)


def resize(image: np.ndarray, width: int, height: int) -> np.ndarray:
    if image.shape[1] == width and image.shape[0] == height:
        return image
    return np.asarray(Image.fromarray(image).resize((width, height), Image.BILINEAR if
                                                    image.shape[0] < height else Image.LANCZOS))


# ------------------------------------------------------------------ geometry helpers


def _weld(positions: np.ndarray, faces: np.ndarray, tol: float = 1e-6):
    keys = np.round(positions / tol).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    new_faces = inverse[faces]
    good = (new_faces[:, 0] != new_faces[:, 1]) & (new_faces[:, 1] != new_faces[:, 2]) & \
           (new_faces[:, 0] != new_faces[:, 2])
    return positions[first], new_faces[good], good


def _vertex_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """`mesh.vertex_normals` on numpy arrays (float64 in and out)."""
    return vertex_normals(torch.from_numpy(positions), torch.from_numpy(faces.astype(np.int64, copy=False))).numpy()


def _subdivide(positions: np.ndarray, faces: np.ndarray):
    """Midpoint subdivision (1 -> 4 triangles), shared edge midpoints."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges.sort(axis=1)
    unique, inverse = np.unique(edges, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    mid = len(positions) + inverse.reshape(3, -1).T  # (F, 3): midpoints of edges 01, 12, 20
    new_positions = np.concatenate([positions, positions[unique].mean(axis=1)])
    a, b, c = faces.T
    ab, bc, ca = mid.T
    new_faces = np.concatenate([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1),
                                np.stack([ca, bc, c], 1), np.stack([ab, bc, ca], 1)])
    return new_positions, new_faces


def _cluster(positions: np.ndarray, faces: np.ndarray, max_verts: int):
    """Vertex clustering on a grid (merges disconnected parts such as leaves), <= max_verts vertices."""
    low, high = 1, 1024
    while low < high:  # the finest grid whose occupied cells fit
        res = (low + high + 1) // 2
        cells = np.floor((positions + 1.0) * 0.5 * res).astype(np.int64)
        if len(np.unique(cells, axis=0)) <= max_verts:
            low = res
        else:
            high = res - 1
    cells = np.floor((positions + 1.0) * 0.5 * low).astype(np.int64)
    _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    merged = np.zeros((len(counts), 3))
    np.add.at(merged, inverse, positions)
    merged /= counts[:, None]
    new_faces = inverse[faces]
    good = (new_faces[:, 0] != new_faces[:, 1]) & (new_faces[:, 1] != new_faces[:, 2]) & \
           (new_faces[:, 0] != new_faces[:, 2])
    new_faces = np.unique(np.sort(new_faces[good], axis=1), axis=0, return_index=True)[1]
    new_faces = inverse[faces][good][np.sort(new_faces)]
    used = np.unique(new_faces)
    remap = np.full(len(merged), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return merged[used], remap[new_faces]


def _closest_faces(points: np.ndarray, tri: np.ndarray, tree: cKDTree, k: int = 8):
    """Index of the original triangle nearest to each point (exact among the k nearest centroids)."""
    k = min(k, len(tri))
    _, candidates = tree.query(points, k=k)
    candidates = candidates.reshape(len(points), k)
    best = np.full(len(points), np.inf)
    choice = candidates[:, 0].copy()
    for j in range(k):
        t = tri[candidates[:, j]]  # (N, 3, 3)
        bary = _barycentric(points, t)
        clamped = np.clip(bary, 0.0, None)
        clamped /= np.maximum(clamped.sum(axis=1, keepdims=True), 1e-12)
        nearest = np.einsum("nk,nkd->nd", clamped, t)
        dist = np.linalg.norm(points - nearest, axis=1)
        better = dist < best - 1e-12
        best[better] = dist[better]
        choice[better] = candidates[better, j]
    return choice


def _barycentric(points: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of the projection of each point onto its triangle's plane."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, points - a
    d00 = (v0 * v0).sum(1)
    d01 = (v0 * v1).sum(1)
    d11 = (v1 * v1).sum(1)
    d20 = (v2 * v0).sum(1)
    d21 = (v2 * v1).sum(1)
    denom = d00 * d11 - d01 * d01
    ok = np.abs(denom) > 1e-20
    denom = np.where(ok, denom, 1.0)
    v = np.where(ok, (d11 * d20 - d01 * d21) / denom, 1 / 3)
    w = np.where(ok, (d00 * d21 - d01 * d20) / denom, 1 / 3)
    return np.stack([1.0 - v - w, v, w], axis=1)


# ------------------------------------------------------------------ atlas


def _build_atlas(raw: RawMesh, corner_uv: np.ndarray, size: int):
    """Pack the used materials into one size x size texture.

    Returns (atlas uint8 (size, size, 3), per-corner atlas uv (F, 3, 2), per-face uv bounds (F, 4)
    = (u0, v0, u1, v1) of the face's cell, or None when the uvs were kept as they are).
    """
    fm = raw.face_material
    corners = raw.positions[raw.faces]
    area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    used = np.unique(fm)
    weight = {int(m): float(area[fm == m].sum()) for m in used}
    textured = [int(m) for m in used if raw.materials[m].texture is not None]
    flat = [int(m) for m in used if raw.materials[m].texture is None]
    if len(textured) == 1 and not flat:
        material = raw.materials[textured[0]]
        image = resize(material.texture, size, size)
        image = np.clip(image * np.clip(material.diffuse, 0, 1), 0, 255).astype(np.uint8)
        return image, corner_uv, None
    textured.sort(key=lambda m: -weight[m])
    if len(textured) > MAX_CELLS - 1:  # the smallest ones become flat colours
        flat += textured[MAX_CELLS - 1:]
        textured = textured[:MAX_CELLS - 1]
    n_cells = len(textured) + (1 if flat else 0)
    grid = int(math.ceil(math.sqrt(n_cells)))
    cell = size // grid
    atlas = np.full((size, size, 3), 128, dtype=np.uint8)
    uv = np.zeros_like(corner_uv)
    bounds = np.zeros((len(fm), 4))
    margin = 1.0 if cell >= 8 else 0.5

    def cell_origin(index):
        row, col = divmod(index, grid)
        return row * cell, col * cell  # top-left pixel

    for index, m in enumerate(textured):
        material = raw.materials[m]
        top, left = cell_origin(index)
        image = resize(material.texture, cell, cell).astype(np.float32) * np.clip(material.diffuse, 0, 1)
        atlas[top:top + cell, left:left + cell] = np.clip(image, 0, 255).astype(np.uint8)
        mask = fm == m
        local = corner_uv[mask]
        local = local - np.floor(local.min(axis=1, keepdims=True))  # per face: bring into [0, ...)
        local = np.clip(local, 0.0, 1.0)
        u0, u1 = (left + margin) / size, (left + cell - margin) / size
        v0, v1 = 1.0 - (top + cell - margin) / size, 1.0 - (top + margin) / size
        uv[mask, :, 0] = u0 + local[..., 0] * (u1 - u0)
        uv[mask, :, 1] = v0 + local[..., 1] * (v1 - v0)
        bounds[mask] = (u0, v0, u1, v1)
    if flat:
        top, left = cell_origin(len(textured))
        swatches = int(math.ceil(math.sqrt(len(flat))))
        swatch = cell / swatches
        for index, m in enumerate(flat):
            material = raw.materials[m]
            if material.texture is not None:
                colour = material.texture.reshape(-1, 3).mean(axis=0) * np.clip(material.diffuse, 0, 1)
            else:
                colour = np.clip(material.diffuse, 0, 1) * 255.0
            row, col = divmod(index, swatches)
            y0, x0 = int(round(top + row * swatch)), int(round(left + col * swatch))
            y1, x1 = int(round(top + (row + 1) * swatch)), int(round(left + (col + 1) * swatch))
            atlas[y0:y1, x0:x1] = np.clip(colour, 0, 255).astype(np.uint8)
            centre_u = (left + (col + 0.5) * swatch) / size
            centre_v = 1.0 - (top + (row + 0.5) * swatch) / size
            mask = fm == m
            uv[mask] = (centre_u, centre_v)
            bounds[mask] = (centre_u, centre_v, centre_u, centre_v)
    return atlas, uv, bounds


# ------------------------------------------------------------------ main entry


def process_mesh(raw: RawMesh, options: ProcessOptions, rng: np.random.Generator,
                 pool: list | None = None) -> Item:
    """Make one fixed-size item from a RawMesh. `pool` is a list of paths or (H, W, 3) uint8 images."""
    positions = raw.positions.astype(np.float64)
    if raw.up_axis == "y":
        positions = positions @ Y_TO_Z.T
    faces = raw.faces
    used = np.unique(faces)
    if len(faces) < 1 or len(used) < 3:
        raise MeshError("mesh has too few faces")
    low, high = positions[used].min(axis=0), positions[used].max(axis=0)
    scale = float((high - low).max()) / 2.0
    if not np.isfinite(scale) or scale <= 1e-12:
        raise MeshError("mesh is degenerate (zero extent)")
    positions = (positions - (low + high) / 2.0) / scale
    raw = RawMesh(positions, faces, raw.uvs, raw.face_material, raw.materials, "z")

    has_texture = raw.uvs is not None and any(
        raw.materials[m].texture is not None for m in np.unique(raw.face_material))
    texture_size = options.texture_size
    bounds = None
    if has_texture:
        texture, corner_uv, bounds = _build_atlas(raw, raw.uvs[raw.faces], texture_size)
        kind, source = "own", "own"

    # geometry: weld by position, drop degenerate faces, simplify or subdivide
    welded, welded_faces, _ = _weld(positions, faces)
    if len(welded_faces) < options.min_faces:
        raise MeshError(f"mesh has only {len(welded_faces)} non-degenerate faces")
    target = options.n_faces
    while len(welded_faces) * 4 <= target:  # small meshes: midpoint subdivision (shape unchanged)
        welded, welded_faces = _subdivide(welded, welded_faces)
    new_positions, new_faces = welded, welded_faces
    if len(new_faces) > target:
        new_positions, new_faces, _ = decimate(welded, welded_faces, target)
        if len(new_faces) > 1.2 * target or len(new_positions) > options.max_verts:
            # the simplifier stalls on many disconnected parts (foliage): cluster vertices first
            welded, welded_faces = _cluster(welded, welded_faces, int(0.6 * options.max_verts))
            if len(welded_faces) < options.min_faces:
                raise MeshError("mesh collapses when simplified")
            new_positions, new_faces = welded, welded_faces
            if len(new_faces) > target:
                new_positions, new_faces, _ = decimate(welded, welded_faces, target)

    for _attempt in range(4):
        if has_texture:
            tri = positions[faces]
            tree = cKDTree(tri.mean(axis=1))
            centroids = new_positions[new_faces].mean(axis=1)
            source_face = _closest_faces(centroids, tri, tree)
            # affine uv map of the source face, evaluated at the new corners
            corner_positions = new_positions[new_faces].reshape(-1, 3)
            source_tri = np.repeat(tri[source_face], 3, axis=0)
            bary = _barycentric(corner_positions, source_tri)
            uv_src = np.repeat(corner_uv[source_face], 3, axis=0)
            uv = np.einsum("nk,nkd->nd", bary, uv_src).reshape(-1, 3, 2)
            if bounds is not None:
                b = bounds[source_face]
                uv[..., 0] = np.clip(uv[..., 0], b[:, None, 0], b[:, None, 2])
                uv[..., 1] = np.clip(uv[..., 1], b[:, None, 1], b[:, None, 3])
            # weld corners by (vertex, uv)
            key_uv = np.round(uv.reshape(-1, 2) * 8192).astype(np.int64)
            keys = np.concatenate([new_faces.reshape(-1, 1), key_uv], axis=1)
            _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
            inverse = inverse.reshape(-1)
            vertex_of = new_faces.reshape(-1)[first]
            out_uvs = uv.reshape(-1, 2)[first]
            out_faces = inverse.reshape(-1, 3)
            out_positions = new_positions[vertex_of]
            out_normals = _vertex_normals(new_positions, new_faces)[vertex_of]
        else:
            out_positions, out_faces = new_positions, new_faces
            out_normals = _vertex_normals(new_positions, new_faces)
            out_uvs = _spherical_uv(new_positions)
        if len(out_positions) <= options.max_verts:
            break
        if has_texture and len(new_positions) <= options.max_verts and _attempt >= 1:
            has_texture, bounds = False, None  # uv seams split too many vertices: spherical uvs instead
            continue
        # too many vertices (after splitting uv seams, or disconnected parts): simplify further
        basis = len(out_positions) if has_texture else len(new_positions)
        target = int(len(new_faces) * options.max_verts / basis * 0.9)
        if target < options.min_faces:
            break
        before = len(new_faces)
        new_positions, new_faces, _ = decimate(welded, welded_faces, target)
        if len(new_faces) > 0.95 * before:
            break  # the simplifier cannot reduce this mesh any further
    if len(out_positions) > options.max_verts or len(out_faces) > options.n_faces:
        # last resort: cluster vertices, simplify, spherical uvs
        welded, welded_faces = _cluster(welded, welded_faces, int(0.6 * options.max_verts))
        new_positions, new_faces = welded, welded_faces
        if len(new_faces) > options.n_faces:
            new_positions, new_faces, _ = decimate(welded, welded_faces, int(0.9 * options.n_faces))
        if len(new_faces) >= options.min_faces:
            has_texture, out_positions, out_faces = False, new_positions, new_faces
            out_normals = _vertex_normals(new_positions, new_faces)
            out_uvs = _spherical_uv(new_positions)
    if len(out_positions) > options.max_verts:
        raise MeshError(f"{len(out_positions)} vertices after simplification exceed the cap {options.max_verts}")

    if not has_texture:
        if pool and rng.random() >= options.p_noise:
            pick = int(rng.integers(len(pool)))
            image = pool[pick]
            source = str(image) if not isinstance(image, np.ndarray) else f"pool[{pick}]"
            if not isinstance(image, np.ndarray):
                image = read_image(image, alpha="drop")
            texture, kind = random_crop(image, rng, texture_size), "real"
        else:
            texture, kind, source = noise_texture(rng, texture_size), "noise", "noise"

    # simplification may move vertices slightly outside the box: normalise the final geometry again
    low, high = out_positions.min(axis=0), out_positions.max(axis=0)
    out_positions = (out_positions - (low + high) / 2.0) / max(float((high - low).max()) / 2.0, 1e-12)
    n_v, n_f = len(out_positions), len(out_faces)
    vmax, fmax = options.max_verts, options.n_faces
    if n_f > fmax:
        raise MeshError(f"{n_f} faces after simplification exceed {fmax}")
    pos = np.zeros((vmax, 3), np.float32)
    nrm = np.zeros((vmax, 3), np.float32)
    uvs = np.zeros((vmax, 2), np.float32)
    fcs = np.zeros((fmax, 3), np.int32)
    pos[:n_v] = out_positions
    nrm[:n_v] = out_normals
    uvs[:n_v] = out_uvs
    fcs[:n_f] = out_faces
    return Item(pos, nrm, uvs, fcs, n_v, n_f, np.ascontiguousarray(texture, dtype=np.uint8), kind, source)


def _spherical_uv(positions: np.ndarray) -> np.ndarray:
    """`mesh.spherical_uv` on numpy arrays (positions already centred, Z-up)."""
    return spherical_uv(torch.from_numpy(positions)).numpy()
