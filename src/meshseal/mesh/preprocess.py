"""Preprocessing used by training and the data builder: normalise, simplify, UVs, normals, up axis."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch

from ..errors import MeshError
from .core import Mesh


def vertex_normals(positions: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted vertex normals (V, 3) from positions (V, 3) and faces (F, 3).

    Where the adjacent faces cancel out (double-sided sheets: each triangle twinned with the opposite
    winding on the same vertices), the faces are first flipped to agree with one of them; shading is
    two-sided, so the sign does not matter but the direction does.
    """
    corners = positions[faces]  # (F, 3, 3)
    face_normals = torch.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0], dim=-1)
    normals = torch.zeros_like(positions)
    magnitude = positions.new_zeros(positions.shape[0])
    reference = torch.zeros_like(positions)
    for k in range(3):
        normals.index_add_(0, faces[:, k], face_normals)
        magnitude.index_add_(0, faces[:, k], face_normals.norm(dim=-1))
        reference.index_copy_(0, faces[:, k], face_normals)
    cancelled = normals.norm(dim=-1) <= 1e-3 * magnitude
    if bool(cancelled.any()):
        agreeing = torch.zeros_like(positions)
        for k in range(3):
            sign = torch.sign((face_normals * reference[faces[:, k]]).sum(-1, keepdim=True))
            agreeing.index_add_(0, faces[:, k], face_normals * sign)
        normals = torch.where(cancelled.unsqueeze(-1), agreeing, normals)
    fallback = torch.tensor([0.0, 0.0, 1.0], dtype=positions.dtype, device=positions.device)
    length = normals.norm(dim=-1, keepdim=True)
    return torch.where(length > 1e-12, normals / length.clamp_min(1e-12), fallback)


def normalize(mesh: Mesh) -> Mesh:
    """Centre the bounding box at the origin and scale uniformly so the largest extent spans [-1, 1]."""
    low, high = mesh.positions.min(dim=0).values, mesh.positions.max(dim=0).values
    scale = (high - low).max().clamp_min(1e-12) / 2.0
    return replace(mesh, positions=(mesh.positions - (low + high) / 2.0) / scale, source=None)


Y_UP_TO_Z_UP = ((1.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0))  # (x, y, z) -> (x, -z, y), a proper rotation


def to_z_up(mesh: Mesh) -> Mesh:
    """Rotate a Y-up mesh into the canonical Z-up frame: (x, y, z) -> (x, -z, y)."""
    if mesh.up_axis == "z":
        return mesh
    rotation = torch.tensor(Y_UP_TO_Z_UP, dtype=mesh.positions.dtype)
    return replace(mesh, positions=mesh.positions @ rotation.T, normals=mesh.normals @ rotation.T,
                   up_axis="z", source=None)


def spherical_uv(positions: torch.Tensor) -> torch.Tensor:
    """Spherical texture coordinates around the origin in the Z-up frame (the seed's mapping)."""
    x, y, z = positions.unbind(-1)
    radius = positions.norm(dim=-1).clamp_min(1e-12)
    u = 0.5 + torch.atan2(y, x) / (2.0 * math.pi)
    v = 0.5 + torch.asin((z / radius).clamp(-1.0, 1.0)) / math.pi
    return torch.stack([u, v], dim=-1)


def subdivide(positions: torch.Tensor, normals: torch.Tensor, uvs: torch.Tensor | None, faces: torch.Tensor,
              times: int = 1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """Each face (F, 3) cut into four at its edges' midpoints, `times` times: positions, normals (V, 3) and
    uvs (V, 2) or None interpolated (normals made unit again), the same surface and texture mapping with
    four times the faces a time; a high-poly asset that looks as the original does (an edge shared by
    two faces gets one midpoint). Returns (positions, normals, uvs, faces)."""
    for _ in range(times):
        edges = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).sort(1).values
        unique, inverse = torch.unique(edges, dim=0, return_inverse=True)
        middle = len(positions) + inverse.reshape(3, -1).T  # (F, 3): the new vertex of edges ab, bc, ca
        positions = torch.cat([positions, positions[unique].mean(1)])
        normals = torch.nn.functional.normalize(torch.cat([normals, normals[unique].mean(1)]), dim=1)
        uvs = None if uvs is None else torch.cat([uvs, uvs[unique].mean(1)])
        a, b, c = faces.unbind(1)
        ab, bc, ca = middle.unbind(1)
        faces = torch.cat([torch.stack(corners, 1) for corners in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return positions, normals, uvs, faces


def decimate(points: np.ndarray, triangles: np.ndarray, target: int, track: bool = False):
    """Quadric-error decimation (fast-simplification) of numpy arrays to at most `target` faces.

    The simplifier may stop a little above the target, so it goes again on its own result (three more
    tries at most, each aiming slightly lower); a mesh it cannot reduce further stays above. Vertices that
    no face uses are dropped. `triangles` must hold more than `target` faces.

    Returns positions (V', 3) float64, faces (F', 3) int64 and, with `track`, the output vertex each
    input vertex collapsed into ((V,) int64, -1 where it ended in no face), else None. Tracking takes
    the result from replaying the recorded collapses, so that the map and the arrays agree: the same
    faces, with positions equal to the simplifier's up to rounding.
    """
    import fast_simplification

    def once(positions, faces, count):
        faces = np.asarray(faces, dtype=np.int32)
        try:
            if not track:
                return (*fast_simplification.simplify(positions, faces, target_count=count), None)
            _, _, collapses = fast_simplification.simplify(positions, faces, target_count=count,
                                                           return_collapses=True)
            new_positions, new_faces, mapping = fast_simplification.replay_simplification(
                positions, faces.astype(np.int64), collapses)
        except (ValueError, RuntimeError) as error:
            raise MeshError(f"simplification failed: {error}") from None
        return new_positions, new_faces, np.asarray(mapping, dtype=np.int64)

    new_points, new_faces, mapping = once(points, triangles, int(target))
    for _ in range(3):
        if len(new_faces) <= target or len(new_faces) <= 4:
            break
        count = min(int(target * 0.97), len(new_faces) - 1)
        new_points, new_faces, again = once(np.asarray(new_points), new_faces, count)
        mapping = None if mapping is None else again[mapping]
    new_faces = np.asarray(new_faces, dtype=np.int64)
    if len(new_faces) == 0:
        raise MeshError("simplification removed every face")
    used = np.unique(new_faces)
    remap = np.full(len(new_points), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return np.asarray(new_points, dtype=np.float64)[used], remap[new_faces], None if mapping is None else remap[mapping]


def _surface_uvs(points: np.ndarray, triangles: np.ndarray, uvs: np.ndarray, new_points: np.ndarray,
                 mapping: np.ndarray) -> torch.Tensor:
    """UVs (V', 2) for decimated vertices `new_points`: each the original `uvs` interpolated at the nearest
    point of the original faces that touch a vertex collapsed into it (`mapping`: original vertex ->
    new vertex or -1)."""
    from trimesh.triangles import closest_point, points_to_barycentric

    corner = mapping[triangles]  # (F, 3): the new vertex each face's corners went to
    pairs = np.unique(np.stack([corner.reshape(-1), np.repeat(np.arange(len(triangles)), 3)], axis=1), axis=0)
    pairs = pairs[pairs[:, 0] >= 0]
    vertex, face = pairs[:, 0], pairs[:, 1]
    corners = points[triangles[face]]
    nearest = closest_point(corners, new_points[vertex])
    distance = np.linalg.norm(nearest - new_points[vertex], axis=1)
    order = np.lexsort((distance, vertex))  # per new vertex, the nearest face first
    first = order[np.r_[True, vertex[order][1:] != vertex[order][:-1]]]
    weights = np.clip(points_to_barycentric(corners[first], nearest[first]), 0.0, 1.0)
    weights /= np.maximum(weights.sum(axis=1, keepdims=True), 1e-12)
    result = np.zeros((len(new_points), 2))
    result[vertex[first]] = np.einsum("fk,fkc->fc", weights, uvs[triangles[face[first]]])
    return torch.from_numpy(result)


def simplify(mesh: Mesh, target_faces: int) -> Mesh:
    """`decimate` a Mesh to at most `target_faces` faces (where the simplifier gets there), keeping its
    attributes.

    The material of each face follows the surviving vertices (each takes that of one original vertex
    that collapsed into it). A vertex's UV is the original's at the nearest point of the faces around
    the vertices that collapsed into it (barycentric), so the texture stays where it was on the surface
    as the vertex moves, and a vertex on a UV seam keeps its own side's chart. Normals are recomputed. A
    mesh already at or below the target is returned unchanged.
    """
    if mesh.n_faces <= target_faces:
        return mesh
    points = mesh.positions.detach().cpu().double().numpy()
    triangles = mesh.faces.cpu().numpy().astype(np.int64)
    new_points, new_faces, mapping = decimate(points, triangles, target_faces, track=True)
    # The attributes of a new vertex come from the first original vertex that collapsed into it.
    representative = np.zeros(len(new_points), dtype=np.int64)
    kept = np.flatnonzero(mapping >= 0)
    representative[mapping[kept[::-1]]] = kept[::-1]
    vertex_material = np.zeros(len(points), dtype=np.int64)
    vertex_material[triangles.reshape(-1)] = np.repeat(mesh.face_material.cpu().numpy(), 3)
    faces = torch.from_numpy(new_faces)
    positions = torch.from_numpy(new_points).to(mesh.positions.dtype)
    uvs = None if mesh.uvs is None else _surface_uvs(points, triangles, mesh.uvs.detach().cpu().double().numpy(),
                                                     new_points, mapping).to(mesh.uvs.dtype)
    face_material = torch.from_numpy(vertex_material[representative][new_faces[:, 0]])
    return replace(mesh, positions=positions, normals=vertex_normals(positions, faces), faces=faces,
                   uvs=uvs, face_material=face_material, source=None)
