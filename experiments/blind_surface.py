"""Blind detection in the seed paper's protocol with a mark laid in surface space, not UV space.

The seed's cameras all stand at x = 0 looking at the origin with z up, so a picture's columns are the
object's x coordinate (up to perspective), whatever the mesh's shape, its UVs or the elevation. The
texture carries a keyed code along the surface's x: every texel is traced to the surface point it
paints (the faces rasterized in UV space), the object's x range is cut into `cells` keyed cells, each
bit a scrambled Walsh-Hadamard code over them, in the default model's blue-yellow chroma and activity
mask. Detection, from the picture alone: whiten the chroma, take the silhouette's column range for the
object's x range, average the object's pixels per cell, search a small stretch and shift, correlate
with the codes. No training.

python experiments/blind_surface.py --data data --meshes 12 --stride 23 --bits 8 --psnr 34
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np
import torch
import torch.nn.functional as F
from blind_lattice import _hadamard, render_pair, seed_protocol_items, sphere_items, whiten
from torch import nn

from meshseal.framing import object_mask
from meshseal.models.spread import COLOURS, activity_mask
from meshseal.render.interpolate import interpolate
from meshseal.render.rasterizer import rasterize

OVERSAMPLE = 4  # detection bins per cell, for the shift search
import os
DIFF = bool(int(os.environ.get("DIFF", "0")))
SEEN = bool(int(os.environ.get("SEEN", "1")))
POOL = float(os.environ.get("POOL", "1"))
CODES = os.environ.get("CODES", "scrambled")
ACROSS = bool(int(os.environ.get("ACROSS", "0")))
ACROSS_Y = float(os.environ.get("ACROSS_Y", "0"))
REFERENCE_EYE = (0.0, -2.5, 3.0)  # the middle of the seed's camera range


def texel_positions(positions: torch.Tensor, faces: torch.Tensor, uvs: torch.Tensor, height: int,
                    width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The surface point (H, W, 3) each texel paints and whether one does (H, W): the faces drawn
    in the UV square (faces across the wrap seam left out), their positions interpolated."""
    corners = uvs[faces.long()]
    keep = (corners.amax(1) - corners.amin(1)).amax(-1) < 0.5
    faces = faces[keep]
    # Where several points share a texel (spherical UVs on a shape that is not star-shaped), the
    # outermost wins: it is the one seen from outside.
    depth = 0.5 - 0.4 * positions.norm(dim=-1, keepdim=True) / positions.norm(dim=-1).max().clamp_min(1e-9)
    clip = torch.cat([2.0 * uvs - 1.0, depth, torch.ones_like(uvs[:, :1])], -1)[None]
    fragments = rasterize(clip.double(), faces, height, width)
    points = interpolate(positions[None].double(), fragments, perspective=False)
    grid = torch.zeros(height * width, 3, dtype=torch.float64)
    grid[fragments.pixel] = points
    painted = torch.zeros(height * width, dtype=torch.bool)
    painted[fragments.pixel] = True
    return grid.reshape(height, width, 3).float(), painted.reshape(height, width)


def reference_columns(points: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
    """Where points (..., 3) appear across the mesh's silhouette, 0 (left) to 1 (right), seen from
    the middle of the seed's camera range: x over depth (perspective), scaled by the vertices'
    range. From any camera of the range a point's column differs from this by a few per cent."""
    eye = torch.tensor(REFERENCE_EYE)
    forward = -eye / eye.norm()
    project = lambda p: p[..., 0] / ((p - eye) * forward).sum(-1)  # noqa: E731
    low, high = project(vertices).min(), project(vertices).max()
    return ((project(points) - low) / (high - low)).clamp(0.0, 1.0)


def seen_columns(positions: torch.Tensor, normals: torch.Tensor, faces: torch.Tensor, uvs: torch.Tensor,
                 vertices: torch.Tensor, height: int, width: int, views: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    """`reference_columns` of the points each texel (H, W) shows from a grid of the seed's cameras
    (views x views eyes), averaged, and whether any view shows it: where several surface points
    share a texel, the ones a picture shows decide its code."""
    from meshseal.render import MeshBatch
    from meshseal.render.cameras import cameras_from_eyes
    from meshseal.render.unrender import surface_at_pixels, surface_points

    ys, zs = torch.linspace(-3.0, -2.0, views), torch.linspace(2.0, 4.0, views)
    eyes = torch.stack([torch.zeros(views * views), ys.repeat_interleave(views), zs.repeat(views)], -1)
    cameras = cameras_from_eyes(eyes)
    batch = MeshBatch.from_tensors(positions[None], normals[None], uvs[None], faces, torch.zeros(1, 3, height, width))
    fragments, uv, _ = surface_at_pixels(batch, cameras, 400, 600)
    points, _ = surface_points(batch, fragments, cameras)
    column = reference_columns(points, vertices).double()
    row = ((1.0 - (uv[:, 1] % 1.0)) * height).long().clamp(0, height - 1)
    col = ((uv[:, 0] % 1.0) * width).long().clamp(0, width - 1)
    index = row * width + col
    total = torch.zeros(height * width, dtype=torch.float64).index_add_(0, index, column)
    count = torch.zeros(height * width, dtype=torch.float64).index_add_(0, index, torch.ones_like(column))
    seen = count > 0
    return (total / count.clamp_min(1.0)).float().reshape(height, width), seen.reshape(height, width)


class SurfaceEncoder(nn.Module):
    """Bits (B, N) -> a blue-yellow mark whose code runs along the surface's x."""

    def __init__(self, n_bits: int, cells: int = 32, texture_psnr: float = 34.0, floor: float = 0.3,
                 window: int = 5, seed: int = 0):
        super().__init__()
        if cells & (cells - 1) or n_bits >= cells:
            raise ValueError("cells must be a power of two above n_bits")
        rng = np.random.default_rng(seed)
        if CODES == "sequency":  # the Walsh functions of fewest sign changes: a shift of a cell costs little
            walsh = _hadamard(cells)
            walsh = walsh[np.argsort((np.diff(walsh, axis=1) != 0).sum(1), kind="stable")]
            rows = walsh[1:n_bits + 1] * rng.choice([-1.0, 1.0], (n_bits, 1))
        else:
            rows = _hadamard(cells)[1 + rng.permutation(cells - 1)[:n_bits]] * rng.choice([-1.0, 1.0], cells)
        self.n_bits, self.cells, self.texture_psnr, self.floor, self.window = n_bits, cells, texture_psnr, floor, window
        self.register_buffer("codes", torch.tensor(rows, dtype=torch.float32))  # (N, cells)
        self.register_buffer("colour", F.normalize(torch.tensor(COLOURS["blue-yellow"]), dim=0))

    def forward(self, texture: torch.Tensor, message: torch.Tensor, texel_x: torch.Tensor,
                painted: torch.Tensor) -> torch.Tensor:
        """texel_x (H, W): each texel's surface x, scaled to [0, 1] over the object."""
        profile = torch.einsum("bk,kc->bc", 2.0 * message - 1.0, self.codes) / math.sqrt(self.n_bits)
        cell = (texel_x * self.cells).long().clamp(0, self.cells - 1)
        field = profile[:, cell] * painted  # (B, H, W)
        residual = activity_mask(texture, self.window, self.floor) * self.colour[None, :, None, None] * field[:, None]
        rms = 10.0 ** (-self.texture_psnr / 20.0)  # over the painted texels: those a picture can show
        power = residual.pow(2).sum(dim=(1, 2, 3), keepdim=True) / (3.0 * painted.sum()).clamp_min(1.0)
        residual = residual * rms / power.sqrt().clamp_min(1e-8)
        return (texture + residual).clamp(0.0, 1.0)


def whiten_across(image: np.ndarray, mask: np.ndarray, colour: np.ndarray, sigma: float) -> np.ndarray:
    """The picture's chroma along the mark's colour minus its mean along the row (a Gaussian of
    `sigma` pixels across, none down: the mark is constant down a column, the host is not), over
    its local RMS. (H, W, 3) -> (H, W), 0 off the object."""
    from scipy import ndimage

    signal = image @ colour
    across = (ACROSS_Y, sigma)
    weight = ndimage.gaussian_filter(mask.astype(float), across) + 1e-6
    detail = (signal - ndimage.gaussian_filter(signal * mask, across) / weight) * mask
    spread = (3 * sigma, 3 * sigma)
    energy = ndimage.gaussian_filter(detail * detail, spread) / ndimage.gaussian_filter(mask.astype(float), spread).clip(1e-6)
    return np.where(mask, detail / np.sqrt(energy + 1e-8), 0.0)


def read(encoder: SurfaceEncoder, image: np.ndarray, mask: np.ndarray, shifts: int, stretches: np.ndarray,
         sigma: float = 2.0) -> np.ndarray:
    """Soft bits (N,) from a picture (H, W, 3) and its object mask: object pixels binned by their
    column over the silhouette's column range, stretched about the centre and shifted, the hypothesis
    whose codes correlate most kept."""
    signal = whiten_across(image, mask, encoder.colour.numpy().astype(np.float64), sigma) if ACROSS else \
        whiten(image, mask, encoder.colour.numpy().astype(np.float64), sigma)
    rows, columns = np.nonzero(mask)
    left, right = columns.min() - 0.5, columns.max() + 0.5
    s = (columns + 0.5 - left) / (right - left)
    values = signal[rows, columns]
    bins = encoder.cells * OVERSAMPLE
    codes = np.repeat(encoder.codes.numpy(), OVERSAMPLE, axis=1)
    best, best_energy = None, -1.0
    for stretch in stretches:
        where = np.floor((0.5 + (s - 0.5) * stretch) * bins).astype(int)
        inside = (where >= 0) & (where < bins)
        total = np.bincount(where[inside], values[inside], bins)
        count = np.bincount(where[inside], None, bins)
        mean = total / np.maximum(count, 1.0) ** POOL
        for shift in range(-shifts, shifts + 1):
            soft = np.roll(codes, shift, axis=1) @ mean
            energy = float(np.abs(soft).sum())
            if energy > best_energy:
                best, best_energy = soft, energy
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="data")
    parser.add_argument("--meshes", type=int, default=12)
    parser.add_argument("--stride", type=int, default=23, help="every stride-th test mesh")
    parser.add_argument("--bits", type=int, default=8)
    parser.add_argument("--cells", type=int, default=32)
    parser.add_argument("--psnr", type=float, default=34.0, help="texture PSNR of the mark")
    parser.add_argument("--shifts", type=int, default=2, help="shifts searched each way (quarter cells)")
    parser.add_argument("--stretches", type=float, nargs="*", default=[1.0])
    parser.add_argument("--sigma", type=float, default=2.0, help="whitening's high-pass (pixels)")
    parser.add_argument("--floor", type=float, default=0.3, help="the activity mask's floor")
    parser.add_argument("--kinds", action="store_true", help="the test items with noise or real textures")
    parser.add_argument("--sphere", action="store_true", help="a UV sphere with noise textures instead")
    parser.add_argument("--width", type=int, default=600)
    parser.add_argument("--height", type=int, default=400)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    encoder = SurfaceEncoder(args.bits, args.cells, args.psnr, floor=args.floor)
    generator = torch.Generator().manual_seed(args.seed)
    rows = []
    if args.sphere:
        items = sphere_items(args.meshes)
    elif args.kinds:  # what `meshseal eval --protocol seed` reads: the split's items with spherical UVs
        from meshseal.data.dataset import MeshDataset

        dataset = MeshDataset(args.data, "test", seed=args.seed, texture_kinds=("noise", "real"))
        items = (dataset[i] for i in range(0, min(args.meshes * args.stride, len(dataset)), args.stride))
    else:
        items = seed_protocol_items(args.data, args.meshes, args.seed, args.stride)
    for item in items:
        message = torch.randint(0, 2, (1, args.bits), generator=generator).float()
        texture = item["texture"][None]
        n_verts = int(item.get("n_verts", len(item["positions"])))
        positions = item["positions"][:n_verts]
        texel, painted = texel_positions(item["positions"], item["faces"], item["uvs"], *texture.shape[-2:])
        texel_x = reference_columns(texel, positions)
        if SEEN:
            columns, seen = seen_columns(item["positions"], item["normals"], item["faces"], item["uvs"], positions,
                                         *texture.shape[-2:])
            texel_x = torch.where(seen, columns, texel_x)
            painted = painted | seen
        with torch.no_grad():
            marked = encoder(texture, message, texel_x, painted)
        original, picture, seen = render_pair(item, texture, marked, generator, args.height, args.width)
        started = time.perf_counter()
        image = picture.numpy().astype(np.float64)
        mask, _ = object_mask(image)
        soft = read(encoder, image, mask, args.shifts, np.array(args.stretches), args.sigma)
        if DIFF:
            image = image - original.numpy().astype(np.float64) + 0.5
            soft = read(encoder, image, mask, args.shifts, np.array(args.stretches), args.sigma)
        clean = read(encoder, original.numpy().astype(np.float64), mask, args.shifts, np.array(args.stretches), args.sigma)
        accuracy = float(((soft > 0) == message[0].bool().numpy()).mean())
        row = {"mesh": item["id"], "bit_acc": accuracy, "clean_bit_acc": float(((clean > 0) == message[0].bool().numpy()).mean()),
               "texture_psnr": float(-10 * torch.log10((marked - texture).pow(2).mean())),
               "painted": float(painted.float().mean()), "seconds": time.perf_counter() - started, **seen}
        rows.append(row)
        print(f"{item['id'][:36]:36s} bits {accuracy:.3f} (unmarked {row['clean_bit_acc']:.3f}) object PSNR "
              f"{seen['psnr_object']:.2f} FLIP {seen['flip_object']:.4f} painted {row['painted']:.2f}", flush=True)
    mean = lambda key: float(np.mean([r[key] for r in rows]))  # noqa: E731
    print(json.dumps({"bits": args.bits, "cells": args.cells, "bit_acc": mean("bit_acc"), "clean_bit_acc": mean("clean_bit_acc"),
                      "psnr_object": mean("psnr_object"), "flip_object": mean("flip_object"),
                      "texture_psnr": mean("texture_psnr")}))


if __name__ == "__main__":
    main()
