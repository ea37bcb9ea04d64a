"""Charts for palette faces, so that a texture mark has texels to lie on.

A face whose three UVs meet at one point (a texture used as a colour palette, or a flat-colour
material packed as a swatch) shows one colour wherever it is seen, and a mark in the texture cannot
spread over it: every pixel of the face shows the same texel. `chart_palette_faces` gives such faces
charts of their own, unwrapped by xatlas (adjacent faces of one colour together, at the texel density
of the mesh's UV-mapped faces): each colour's charts in a block that colour fills, the blocks packed
into rows added below the texture with wide gutters, so that filtering and mip levels keep every
face's colour. The rest of the texture keeps its texels, and the rows and columns it wraps onto
are copied next to it, so the charted mesh renders as the original did; a mark then lies on the
charts as on any UV-mapped surface. It is deterministic: detection charts the original the same way
and reads the mark where embedding put it.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch

from ..mesh.core import Mesh

CHART_ABOVE = 0.1  # chart when this share of the textured surface is on palette faces
POINT_TEXELS = 1.0  # a palette face's UVs lie within this many texels of each other
GUTTER = 4  # texels between two colours' blocks, filled half by each: the first mip levels keep both
MAX_SIDE = 4096  # the atlas's largest side; its density is lowered to fit
# A pixel of a 256^2 view of a radius-1 object 3.5 away with a 60-degree field: `models.spread.PIXEL_AT_OBJECT`
# rounded. The rounded value stays because it fixes the chart layouts (the exact one would move a few of them).
STANDARD_PIXEL = 1 / 63.3
TEXELS_PER_PIXEL = 2.0  # at most this many chart texels per pixel of that view (more is never seen)


def palette_faces(mesh: Mesh, material: int) -> torch.Tensor:
    """Indices of `material`'s faces without UV area whose UVs meet at a point (within POINT_TEXELS
    texels). A charted face has UV area, so charting twice changes nothing."""
    texture = mesh.materials[material].texture
    height, width = texture.shape[:2]
    faces = torch.nonzero(mesh.face_material == material).squeeze(1)
    corners = mesh.uvs.double()[mesh.faces[faces]]
    first, second = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    area = 0.5 * (first[:, 0] * second[:, 1] - first[:, 1] * second[:, 0]).abs()
    spread = ((corners.amax(1) - corners.amin(1)) * torch.tensor([width, height], dtype=torch.float64)).amax(1)
    return faces[(area <= 1e-12) & (spread <= POINT_TEXELS)]


def palette_surface_share(mesh: Mesh) -> float:
    """The share of the textured surface on palette faces (`palette_faces`)."""
    if mesh.uvs is None:
        return 0.0
    area = _surface(mesh.positions.double(), mesh.faces)
    textured = torch.tensor([m.texture is not None for m in mesh.materials])[mesh.face_material]
    total = float(area[textured].sum())
    if total <= 0:
        return 0.0
    on_palette = sum(float(area[palette_faces(mesh, index)].sum())
                     for index, m in enumerate(mesh.materials) if m.texture is not None)
    return on_palette / total


def chart_palette_faces(mesh: Mesh) -> Mesh:
    """`mesh` with its palette faces charted (module docstring), or `mesh` itself where under
    CHART_ABOVE of the textured surface is on palette faces or no texture can take charts. New
    vertices follow their part's own vertices (a file's structure is kept for saving); the instances
    of one geometry are charted alike."""
    if mesh.uvs is None or palette_surface_share(mesh) < CHART_ABOVE:
        return mesh
    parts = _parts(mesh)
    first = {}
    for part in parts:
        first.setdefault(part[0], part)
    charted = {}  # material -> (texture, uv map of its old texels, {part key: (faces, vertices, uvs)})
    for index, material in enumerate(mesh.materials):
        if material.texture is not None:
            result = _chart_material(mesh, index, list(first.values()))
            if result is not None:
                charted[index] = result
    if not charted:
        return mesh
    return _assemble(mesh, parts, charted)


def _chart_material(mesh: Mesh, material: int, parts: list) -> tuple | None:
    """One material's charts: its new texture, the affine map (scale, offset) of its old UVs into it,
    and per geometry key the palette faces of its first instance (mesh indices), the new vertices'
    sources (indices within the part) with the faces on them, and the new vertices' UVs, per colour."""
    texture = mesh.materials[material].texture
    height, width = texture.shape[:2]
    palette = palette_faces(mesh, material)
    if len(palette) == 0:
        return None
    mapped = torch.nonzero(mesh.face_material == material).squeeze(1)
    mapped = mapped[~torch.isin(mapped, palette)]
    old_uvs = mesh.uvs[mesh.faces[mapped].reshape(-1)]
    if len(mapped) and (bool((old_uvs < -1e-6).any()) or bool((old_uvs > 1 + 1e-6).any())):
        return None  # a tiled texture (UVs past its edges) cannot be moved into part of a larger one
    if _shared_with_other_materials(mesh, material):
        return None
    colours = _face_colours(texture, mesh.uvs, mesh.faces[palette])
    quantised = (colours * 255).round().long()
    colour_key = quantised[:, 0] * 65536 + quantised[:, 1] * 256 + quantised[:, 2]
    groups = []  # (part key, part vertex start, face indices (global), colour)
    for key, vertices, faces in parts:
        in_part = (palette >= faces.start) & (palette < faces.stop)
        for colour in torch.unique(colour_key[in_part]).tolist():
            chosen = in_part & (colour_key == colour)
            groups.append((key, vertices.start, palette[chosen], colours[chosen][0]))
    if not groups:
        return None
    density = _density(mesh, mapped, height, width)
    while True:
        blocks = _unwrap(mesh, [faces for _, _, faces, _ in groups], density)
        places, atlas_width, atlas_height = _shelves([(w, h) for (h, w), _, _, _ in blocks], width)
        if max(atlas_width, atlas_height) <= MAX_SIDE:
            break
        density *= 0.95 * MAX_SIDE / max(atlas_width, atlas_height)
    # Layout: the old texture, under it a copy of its top row (what its bottom row wraps onto), the
    # atlas, then a copy of its bottom row (what its top row wraps onto); the old texture's right-hand
    # neighbour columns likewise where the atlas is wider.
    new_width = width if atlas_width <= width else atlas_width + 2
    new_height = height + 1 + atlas_height + 1
    image = torch.zeros(new_height, new_width, 3)
    image[:height, :width] = texture
    image[height] = _row(texture[0], new_width)
    image[-1] = _row(texture[-1], new_width)
    if new_width > width:
        image[:height, width] = texture[:, 0]
        image[:height, width + 1:] = texture[:, -1:].expand(-1, new_width - width - 1, -1)
    paint = np.zeros((atlas_height, atlas_width, 3), dtype=np.float32)
    owned = np.zeros((atlas_height, atlas_width), dtype=bool)
    by_part = {}
    for (key, start, faces, colour), (block, sources, indices, texels), (left, top) in zip(groups, blocks, places):
        block_height, block_width = block
        paint[top: top + block_height, left: left + block_width] = colour.numpy()
        owned[top: top + block_height, left: left + block_width] = True
        row = texels[:, 1] + top + height + 1
        new_uvs = torch.from_numpy(np.stack([(texels[:, 0] + left) / new_width, 1 - row / new_height], 1)).float()
        used = torch.unique(mesh.faces[faces].reshape(-1))
        entry = by_part.setdefault(key, ([], [], []))
        entry[0].append(faces)
        entry[1].append((used[torch.from_numpy(sources)] - start, torch.from_numpy(indices)))
        entry[2].append(new_uvs)
    if owned.any():  # the gutters between blocks take the nearest block's colour
        from scipy import ndimage  # only a mesh with palette faces gets here: not on every reading's import path

        _, (nearest_rows, nearest_cols) = ndimage.distance_transform_edt(~owned, return_indices=True)
        paint = paint[nearest_rows, nearest_cols]
    image[height + 1: height + 1 + atlas_height, :atlas_width] = torch.from_numpy(paint)
    scale = torch.tensor([width / new_width, height / new_height])
    offset = torch.tensor([0.0, 1.0 - height / new_height])
    return image, (scale, offset), by_part


def _assemble(mesh: Mesh, parts: list, charted: dict) -> Mesh:
    """The charted mesh: each part's vertices (old UVs mapped into the new textures), then its new
    chart vertices; the palette faces re-indexed onto them."""
    materials = [replace(m, texture=charted[i][0]) if i in charted else replace(m)
                 for i, m in enumerate(mesh.materials)]
    uvs = mesh.uvs.clone()
    for index, (_, (scale, offset), _) in charted.items():
        vertices = torch.unique(mesh.faces[mesh.face_material == index].reshape(-1))
        uvs[vertices] = uvs[vertices] * scale + offset
    positions, normals, new_uvs, faces = [], [], [], mesh.faces.clone()
    new_parts, count = [], 0
    for part_index, (key, vertices, part_faces) in enumerate(parts):
        positions.append(mesh.positions[vertices])
        normals.append(mesh.normals[vertices])
        new_uvs.append(uvs[vertices])
        shift = count - vertices.start
        faces[part_faces] += shift
        added = vertices.stop - vertices.start
        for _, _, by_part in charted.values():
            if key not in by_part:
                continue
            first_faces, sources, chart_uvs = by_part[key]
            first_face_start = next(f.start for k, v, f in parts if k == key)
            for group_faces, (local_sources, indices), group_uvs in zip(first_faces, sources, chart_uvs):
                positions.append(mesh.positions[vertices.start + local_sources])
                normals.append(mesh.normals[vertices.start + local_sources])
                new_uvs.append(group_uvs)
                here = group_faces - first_face_start + part_faces.start  # the same faces in this instance
                faces[here] = indices + count + added
                added += len(local_sources)
        new_parts.append((part_index, slice(count, count + added)))
        count += added
    charted_mesh = replace(mesh, positions=torch.cat(positions), normals=torch.cat(normals), uvs=torch.cat(new_uvs),
                           faces=faces, face_material=mesh.face_material.clone(), materials=materials)
    if mesh.source is not None:
        source_parts = [replace(p, vertices=s) for p, (_, s) in zip(mesh.source.parts, new_parts)]
        charted_mesh.source = replace(mesh.source, parts=source_parts)
    return charted_mesh


def _parts(mesh: Mesh) -> list[tuple[str, slice, slice]]:
    """(geometry key, vertex slice, face slice) of each part: the file's parts, or the whole mesh."""
    if mesh.source is not None and getattr(mesh.source, "parts", None):
        return [(p.geometry, p.vertices, p.faces) for p in mesh.source.parts]
    return [("mesh", slice(0, mesh.n_vertices), slice(0, mesh.n_faces))]


def _shared_with_other_materials(mesh: Mesh, material: int) -> bool:
    """True when a vertex of `material`'s faces is also a vertex of another material's faces (moving
    its UV would move theirs)."""
    own = mesh.face_material == material
    mine = torch.zeros(mesh.n_vertices, dtype=torch.bool)
    mine[mesh.faces[own].reshape(-1)] = True
    return bool(mine[mesh.faces[~own].reshape(-1)].any())


def _face_colours(texture: torch.Tensor, uvs: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    """The colour (F, 3) each palette face shows: the texture at its UV point, as the renderer samples it."""
    from ..render.texture import sample_texture

    return sample_texture(texture.permute(2, 0, 1).float(), uvs[corners].mean(1).float())


def _surface(positions: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    corners = positions[faces]
    return 0.5 * torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]).norm(dim=1)


def _density(mesh: Mesh, mapped: torch.Tensor, height: int, width: int) -> float:
    """Chart texels per unit length: the area-weighted median of the material's UV-mapped faces,
    at most TEXELS_PER_PIXEL per pixel of a standard view of the object."""
    positions = mesh.positions.double()
    radius = float((positions - (positions.amax(0) + positions.amin(0)) / 2).norm(dim=1).max())
    cap = TEXELS_PER_PIXEL / (STANDARD_PIXEL * max(radius, 1e-12))
    if len(mapped) == 0:
        return cap
    surface = _surface(positions, mesh.faces[mapped])
    corners = mesh.uvs.double()[mesh.faces[mapped]] * torch.tensor([width, height], dtype=torch.float64)
    first, second = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    texels = 0.5 * (first[:, 0] * second[:, 1] - first[:, 1] * second[:, 0]).abs()
    usable = (surface > 0) & (texels > 0)
    if not bool(usable.any()):
        return cap
    density, weight = (texels[usable] / surface[usable]).sqrt(), surface[usable]
    order = torch.argsort(density)
    cumulative = torch.cumsum(weight[order], 0)
    median = float(density[order][min(int(torch.searchsorted(cumulative, cumulative[-1] / 2)), len(order) - 1)])
    return min(median, cap) if math.isfinite(median) else cap


def _row(row: torch.Tensor, width: int) -> torch.Tensor:
    """A texture row (W, 3) widened to `width` by repeating its last texel."""
    return torch.cat([row, row[-1:].expand(width - len(row), -1)]) if width > len(row) else row


def _unwrap(mesh: Mesh, groups: list[torch.Tensor],
            density: float) -> list[tuple[tuple[int, int], np.ndarray, np.ndarray, np.ndarray]]:
    """Each group of faces (one part's faces of one colour) unwrapped by xatlas at `density` texels
    per unit length (in a child process: `methods.unwrap`): the size (h, w) of the block that the
    colour fills (so that no filtering between its charts changes a colour), the new vertices'
    sources (indices into the faces' sorted vertices), the faces on them, and their texel positions
    (x right, y down) in the block."""
    from .unwrap import unwrap_many

    jobs = []
    for faces in groups:
        used, local = torch.unique(mesh.faces[faces].reshape(-1), return_inverse=True)
        jobs.append((mesh.positions[used].double().numpy(), local.reshape(-1, 3).numpy().astype(np.uint32), density))
    return unwrap_many(jobs)


def _shelves(sizes: list[tuple[int, int]], width: int) -> tuple[list[tuple[int, int]], int, int]:
    """Blocks (w, h) placed on shelves (the tallest first) GUTTER texels apart, the shelves as wide as
    the texture, the widest block or a square holding them all: each block's (left, top), and the
    atlas's width and height."""
    order = sorted(range(len(sizes)), key=lambda i: (-sizes[i][1], i))
    area = sum((w + GUTTER) * (h + GUTTER) for w, h in sizes)
    shelf_width = max([width, math.ceil(math.sqrt(area)) + GUTTER] + [w + 2 * GUTTER for w, _ in sizes])
    places, x, y, shelf_height = [None] * len(sizes), GUTTER, GUTTER, 0
    for index in order:
        w, h = sizes[index]
        if x + w + GUTTER > shelf_width:
            x, y, shelf_height = GUTTER, y + shelf_height + GUTTER, 0
        places[index] = (x, y)
        x, shelf_height = x + w + GUTTER, max(shelf_height, h)
    return places, shelf_width, y + shelf_height + GUTTER
