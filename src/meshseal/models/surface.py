"""A blind mark laid in surface space: a keyed code along the object's x, read from a picture alone.

The seed paper's cameras all stand at x = 0 looking at the object with z up (only the distance and
the elevation vary), so a picture's columns follow the object's x whatever its shape, its UVs or the
elevation. The texture carries the bits along x: every texel is traced to the surface point it paints,
the object's x range (as seen from the middle of the seed's camera range, perspective included) is cut
into `cells` cells, and each bit is a scrambled Walsh-Hadamard code over them (drawn from the config's
`pattern_seed`; a user's key whitens the payload bits, not this pattern), in blue-yellow chroma under a
just-noticeable-difference mask. A picture is read with no mesh: the object's column
range is the object's x range, the chroma is high-passed along rows (the mark is constant down a
column, the host is not), averaged per cell and correlated with each bit's code. Nothing is learned.

What limits it (docs/mark.md, "The blind surface code"): a texel must paint one x, so textures
shared across the object (spherical UVs on shapes that are not star-shaped, mirrored or tiled UVs) blur
the code; and the cameras must keep the seed's azimuth: a view from the side shows the code edge-on.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from .spread import USED_RESOLUTION, activity_mask, colour_direction

REFERENCE_EYE = (0.0, -2.5, 3.0)  # the middle of the seed's camera range (canonical frame, z up)
SEED_VIEWS = 3  # texels are traced through SEED_VIEWS^2 cameras of the seed's range
VIEW_SIZE = (400, 600)  # the seed paper's picture (height, width)
OVERSAMPLE = 4  # detection bins per cell, for the shift search
SHIFTS = 2  # shifts searched each way, in bins
HIGHPASS = 0.025  # the row high-pass's Gaussian, as a share of the object's width in the picture
POOL = 0.5  # a cell's evidence: the sum of its pixels over count^POOL (0: sum, 1: mean)


def _hadamard(n: int) -> np.ndarray:
    matrix = np.ones((1, 1))
    while matrix.shape[0] < n:
        matrix = np.block([[matrix, matrix], [matrix, -matrix]])
    return matrix


def reference_columns(points: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
    """Where points (..., 3) appear across the mesh's silhouette, 0 (left) to 1 (right), seen from
    the middle of the seed's camera range: x over depth (perspective), scaled by the vertices'
    (V, 3) range. From any camera of the range a point's column differs from this by a few per cent."""
    eye = torch.tensor(REFERENCE_EYE, dtype=points.dtype, device=points.device)
    forward = -eye / eye.norm()
    project = lambda p: p[..., 0] / ((p - eye) * forward).sum(-1)  # noqa: E731
    seen = project(vertices.to(points))
    return ((project(points) - seen.min()) / (seen.max() - seen.min()).clamp_min(1e-9)).clamp(0.0, 1.0)


def _uv_raster(positions: torch.Tensor, faces: torch.Tensor, uvs: torch.Tensor, height: int,
               width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The surface point (H, W, 3) each texel paints and whether one does (H, W): the faces drawn in
    the UV square (faces across the wrap seam left out). Where several points share a texel (spherical
    UVs on a shape that is not star-shaped), the outermost wins: it is the one seen from outside."""
    from ..render.interpolate import interpolate
    from ..render.rasterizer import rasterize

    wrapped = uvs - torch.floor(uvs)  # repeating textures: every face near the first UV square
    corners = wrapped[faces.long()]
    faces = faces[(corners.amax(1) - corners.amin(1)).amax(-1) < 0.5]
    radius = positions.norm(dim=-1, keepdim=True)
    depth = 0.5 - 0.4 * radius / radius.max().clamp_min(1e-9)
    clip = torch.cat([2.0 * wrapped - 1.0, depth, torch.ones_like(depth)], -1)[None].double()
    grid = torch.zeros(height * width, 3, dtype=torch.float64)
    painted = torch.zeros(height * width, dtype=torch.bool)
    if len(faces):
        fragments = rasterize(clip, faces, height, width)
        grid[fragments.pixel] = interpolate(positions[None].double(), fragments, perspective=False)
        painted[fragments.pixel] = True
    return grid.reshape(height, width, 3).float(), painted.reshape(height, width)


def seen_texels(positions: torch.Tensor, normals: torch.Tensor, faces: torch.Tensor, uvs: torch.Tensor,
                height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Every object pixel of a grid of the seed's cameras (SEED_VIEWS^2 views at VIEW_SIZE): the
    `reference_columns` of the point it shows (P,) float64 and the texel (flat index into H x W) it
    shows it with (P,)."""
    from ..render import MeshBatch
    from ..render.cameras import cameras_from_eyes
    from ..render.unrender import surface_at_pixels, surface_points

    ys, zs = torch.linspace(-3.0, -2.0, SEED_VIEWS), torch.linspace(2.0, 4.0, SEED_VIEWS)
    eyes = torch.stack([torch.zeros(SEED_VIEWS ** 2), ys.repeat_interleave(SEED_VIEWS), zs.repeat(SEED_VIEWS)], -1)
    cameras = cameras_from_eyes(eyes)
    batch = MeshBatch.from_tensors(positions[None], normals[None], uvs[None], faces, torch.zeros(1, 3, 1, 1))
    fragments, uv, _ = surface_at_pixels(batch, cameras, *VIEW_SIZE)
    points, _ = surface_points(batch, fragments, cameras)
    row = ((1.0 - (uv[:, 1] % 1.0)) * height).long().clamp(0, height - 1)
    col = ((uv[:, 0] % 1.0) * width).long().clamp(0, width - 1)
    return reference_columns(points.double(), positions.double()), row * width + col


def _seen(positions: torch.Tensor, normals: torch.Tensor, faces: torch.Tensor, uvs: torch.Tensor,
          height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The mean column (H, W) of the points each texel shows in `seen_texels`, and whether any
    view shows it."""
    column, index = seen_texels(positions, normals, faces, uvs, height, width)
    total = torch.zeros(height * width, dtype=torch.float64).index_add_(0, index, column)
    count = torch.zeros(height * width, dtype=torch.float64).index_add_(0, index, torch.ones_like(column))
    return (total / count.clamp_min(1.0)).float().reshape(height, width), (count > 0).reshape(height, width)


@torch.no_grad()
def texel_columns(positions: torch.Tensor, normals: torch.Tensor, faces: torch.Tensor, uvs: torch.Tensor,
                  height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Each texel's column (H, W) in [0, 1] (`reference_columns` of the surface point it paints) and
    whether it paints any (H, W) bool, for a mesh in the canonical frame (positions (V, 3), faces
    (F, 3) of this texture, uvs (V, 2)). Texels the seed's views show take the columns they are seen
    at; the rest, the point the UV map puts them on. Worked out at most USED_RESOLUTION texels a side."""
    positions, normals, uvs = (t.detach().float().cpu() for t in (positions, normals, uvs))
    faces = faces.detach().long().cpu()
    h, w = min(height, USED_RESOLUTION), min(width, USED_RESOLUTION)
    points, painted = _uv_raster(positions, faces, uvs, h, w)
    columns = reference_columns(points, positions)
    seen_columns, seen = _seen(positions, normals, faces, uvs, h, w)
    columns, painted = torch.where(seen, seen_columns, columns), painted | seen
    if (h, w) != (height, width):
        columns = F.interpolate(columns[None, None], size=(height, width), mode="nearest")[0, 0]
        painted = F.interpolate(painted[None, None].float(), size=(height, width), mode="nearest")[0, 0] > 0
    return columns, painted


class SurfaceCodeEncoder(nn.Module):
    """Bits (B, N) -> a blue-yellow mark whose keyed code runs along the surface's x."""

    def __init__(self, n_bits: int, cells: int = 32, colour: str = "blue-yellow", texture_psnr: float = 28.0,
                 window: int = 5, floor: float = 3.0, seed: int = 0):
        super().__init__()
        if cells & (cells - 1) or not 0 < n_bits < cells:
            raise ValueError("cells must be a power of two above n_bits")
        rng = np.random.default_rng(seed)
        rows = _hadamard(cells)[1 + rng.permutation(cells - 1)[:n_bits]] * rng.choice([-1.0, 1.0], cells)
        self.n_bits, self.cells, self.texture_psnr, self.window, self.floor = n_bits, cells, texture_psnr, window, floor
        self.register_buffer("codes", torch.tensor(rows, dtype=torch.float32))  # (N, cells)
        self.register_buffer("colour", colour_direction(colour))

    def forward(self, texture: torch.Tensor, message: torch.Tensor, columns: torch.Tensor, painted: torch.Tensor,
                strength: float = 1.0) -> torch.Tensor:
        """Textures (B, 3, H, W) marked with messages (B, N); columns, painted (B, H, W) from
        `texel_columns`. The mark's RMS over the painted texels is `strength` times texture_psnr's."""
        profile = torch.einsum("bk,kc->bc", 2.0 * message - 1.0, self.codes) / math.sqrt(self.n_bits)
        cell = (columns * self.cells).long().clamp(0, self.cells - 1)
        field = torch.gather(profile, 1, cell.flatten(1)).reshape(cell.shape) * painted  # (B, H, W)
        residual = activity_mask(texture, self.window, self.floor) * self.colour[None, :, None, None] * field[:, None]
        power = residual.pow(2).sum(dim=(1, 2, 3), keepdim=True) / (3.0 * painted.sum(dim=(1, 2)).view(-1, 1, 1, 1)).clamp_min(1.0)
        rms = strength * 10.0 ** (-self.texture_psnr / 20.0)
        return (texture + residual * rms / power.sqrt().clamp_min(1e-8)).clamp(0.0, 1.0)


def _whiten_across(signal: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """`signal` (H, W) minus its mean along the row (a Gaussian of `sigma` pixels across, none down:
    the mark is constant down a column, the host is not), over its local RMS; 0 off the object."""
    from scipy import ndimage

    weight = ndimage.gaussian_filter(mask.astype(float), (0.0, sigma)) + 1e-6
    detail = (signal - ndimage.gaussian_filter(signal * mask, (0.0, sigma)) / weight) * mask
    spread = 3.0 * sigma
    energy = ndimage.gaussian_filter(detail * detail, spread) / ndimage.gaussian_filter(mask.astype(float), spread).clip(1e-6)
    return np.where(mask, detail / np.sqrt(energy + 1e-8), 0.0)


def read_picture(encoder: SurfaceCodeEncoder, image: np.ndarray, mask: np.ndarray,
                 signal: np.ndarray | None = None) -> torch.Tensor:
    """Soft bits (N,) of a picture (H, W, 3) in [0, 1] whose object covers `mask` (H, W) bool: the
    object's pixels binned by their place in its column range, shifted a little, and the shift whose
    codes correlate most kept (sign: the bit). `signal` (H, W): another whitened chroma to read
    instead of the row high-pass's (experiments)."""
    rows, columns = np.nonzero(mask)
    if len(columns) == 0:
        return torch.zeros(encoder.n_bits)
    left, right = columns.min() - 0.5, columns.max() + 0.5
    if signal is None:
        chroma = image.astype(np.float64) @ encoder.colour.cpu().numpy().astype(np.float64)
        signal = _whiten_across(chroma, mask, max(1.0, HIGHPASS * (right - left)))
    bins = encoder.cells * OVERSAMPLE
    where = np.clip(np.floor((columns + 0.5 - left) / (right - left) * bins).astype(int), 0, bins - 1)
    total = np.bincount(where, signal[rows, columns], bins)
    evidence = total / np.maximum(np.bincount(where, None, bins), 1.0) ** POOL
    codes = np.repeat(encoder.codes.cpu().numpy().astype(np.float64), OVERSAMPLE, axis=1)
    softs = [np.roll(codes, shift, axis=1) @ evidence for shift in range(-SHIFTS, SHIFTS + 1)]
    best = max(softs, key=lambda soft: float(np.abs(soft).sum()))
    return torch.from_numpy(best / math.sqrt(max(float(evidence @ evidence), 1e-12))).float()
