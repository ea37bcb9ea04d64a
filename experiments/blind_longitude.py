"""Blind detection in the seed paper's protocol with a code that varies along longitude only.

The seed's cameras all stand at x = 0, y < 0 (only the distance and the elevation vary), so with
spherical UVs every picture shows the same half of the longitudes, in the same left-to-right order,
while the elevation decides which latitudes. A mark that is constant along v (latitude) and carries the
bits along u (longitude) is then read the same from every view of the range. Texture: 64 keyed u-cells,
each bit a scrambled Walsh-Hadamard code over them (spread spectrum), in the default model's
blue-yellow chroma and activity mask. Detection, from the picture alone: whiten the chroma (as
`blind_lattice.py`), take each object pixel for a point of the sphere inscribed in the object's box
seen from the seed's side, average per u-cell, search the elevation and a small shift of u, and
correlate with each bit's code. No training. Not shipped: see docs/training.md.

python experiments/blind_longitude.py --data data --meshes 12 --stride 23 --bits 8 --psnr 34
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np
import torch
import torch.nn.functional as F
from blind_lattice import render_pair, seed_protocol_items, sphere_items, whiten
from torch import nn

from meshseal.framing import object_mask
from meshseal.models.spread import COLOURS, activity_mask
from meshseal.models.surface import _hadamard

OVERSAMPLE = 4  # detection bins per u-cell, for the shift search


class LongitudeEncoder(nn.Module):
    """Bits (B, N) -> a blue-yellow mark constant along v, keyed codes along u."""

    def __init__(self, n_bits: int, cells: int = 64, texture_psnr: float = 34.0, floor: float = 0.3,
                 window: int = 5, seed: int = 0):
        super().__init__()
        if cells & (cells - 1) or n_bits >= cells:
            raise ValueError("cells must be a power of two above n_bits")
        rng = np.random.default_rng(seed)
        rows = _hadamard(cells)[1 + rng.permutation(cells - 1)[:n_bits]] * rng.choice([-1.0, 1.0], cells)
        self.n_bits, self.cells, self.texture_psnr, self.floor, self.window = n_bits, cells, texture_psnr, floor, window
        self.register_buffer("codes", torch.tensor(rows, dtype=torch.float32))  # (N, cells)
        self.register_buffer("colour", F.normalize(torch.tensor(COLOURS["blue-yellow"]), dim=0))

    def forward(self, texture: torch.Tensor, message: torch.Tensor) -> torch.Tensor:
        width = texture.shape[-1]
        profile = torch.einsum("bk,kc->bc", 2.0 * message - 1.0, self.codes) / math.sqrt(self.n_bits)
        column = profile[:, (torch.arange(width) * self.cells) // width]  # (B, W): u grows with the column
        residual = activity_mask(texture, self.window, self.floor) * self.colour[None, :, None, None] * column[:, None, None, :]
        rms = 10.0 ** (-self.texture_psnr / 20.0)
        residual = residual * rms / residual.pow(2).mean(dim=(1, 2, 3), keepdim=True).sqrt().clamp_min(1e-8)
        return (texture + residual).clamp(0.0, 1.0)


def read(encoder: LongitudeEncoder, image: np.ndarray, mask: np.ndarray, shifts: int,
         elevations: np.ndarray) -> np.ndarray:
    """Soft bits (N,) from a picture (H, W, 3) and its object mask (H, W): each object pixel is taken
    for a point of the sphere inscribed in the object's box, seen (orthographically) from the seed's
    side at each of `elevations` (radians); the elevation and the u shift whose codes correlate most
    are kept."""
    signal = whiten(image, mask, encoder.colour.numpy().astype(np.float64))
    rows, columns = np.nonzero(mask)
    centre_y, centre_x = (rows.min() + rows.max()) / 2.0, (columns.min() + columns.max()) / 2.0
    radius = max(rows.max() - rows.min(), columns.max() - columns.min()) / 2.0 + 0.5
    x, y = (columns - centre_x) / radius, -(rows - centre_y) / radius
    inside = x * x + y * y < 0.9  # off the rim, where the longitude changes fastest
    x, y, values = x[inside], y[inside], signal[rows[inside], columns[inside]]
    depth = np.sqrt(1.0 - x * x - y * y)
    bins = encoder.cells * OVERSAMPLE
    codes = np.repeat(encoder.codes.numpy(), OVERSAMPLE, axis=1)  # (N, bins)
    best, best_energy = None, -1.0
    for elevation in elevations:
        # Camera at (0, -cos e, sin e): right (1, 0, 0), up (0, sin e, cos e), towards it (0, -cos e, sin e).
        world_x = x
        world_y = y * math.sin(elevation) - depth * math.cos(elevation)
        u = 0.5 + np.arctan2(world_y, world_x) / (2 * math.pi)
        where = np.floor(u * bins).astype(int) % bins
        total, count = np.bincount(where, values, bins), np.bincount(where, None, bins)
        mean = np.where(count > 0, total / np.maximum(count, 1.0), 0.0)
        for shift in range(-shifts, shifts + 1):  # the mapping's offset, a quarter cell a step
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
    parser.add_argument("--cells", type=int, default=64)
    parser.add_argument("--psnr", type=float, default=34.0, help="texture PSNR of the mark")
    parser.add_argument("--elevations", type=int, default=8, help="camera elevations searched (34-63 degrees)")
    parser.add_argument("--shifts", type=int, default=4, help="u shifts searched each way (quarter cells)")
    parser.add_argument("--sphere", action="store_true", help="a UV sphere with noise textures instead")
    parser.add_argument("--width", type=int, default=600)
    parser.add_argument("--height", type=int, default=400)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    encoder = LongitudeEncoder(args.bits, args.cells, args.psnr)
    generator = torch.Generator().manual_seed(args.seed)
    elevations = np.radians(np.linspace(34.0, 63.0, args.elevations))
    rows = []
    items = sphere_items(args.meshes) if args.sphere else seed_protocol_items(args.data, args.meshes, args.seed, args.stride)
    for item in items:
        message = torch.randint(0, 2, (1, args.bits), generator=generator).float()
        texture = item["texture"][None]
        with torch.no_grad():
            marked = encoder(texture, message)
        original, picture, seen = render_pair(item, texture, marked, generator, args.height, args.width)
        started = time.perf_counter()
        image = picture.numpy().astype(np.float64)
        mask, _ = object_mask(image)
        soft = read(encoder, image, mask, args.shifts, elevations)
        clean = read(encoder, original.numpy().astype(np.float64), mask, args.shifts, elevations)
        accuracy = float(((soft > 0) == message[0].bool().numpy()).mean())
        row = {"mesh": item["id"], "bit_acc": accuracy, "clean_bit_acc": float(((clean > 0) == message[0].bool().numpy()).mean()),
               "texture_psnr": float(-10 * torch.log10((marked - texture).pow(2).mean())),
               "seconds": time.perf_counter() - started, **seen}
        rows.append(row)
        print(f"{item['id'][:36]:36s} bits {accuracy:.3f} (unmarked {row['clean_bit_acc']:.3f}) object PSNR "
              f"{seen['psnr_object']:.2f} FLIP {seen['flip_object']:.4f}", flush=True)
    mean = lambda key: float(np.mean([r[key] for r in rows]))  # noqa: E731
    print(json.dumps({"bits": args.bits, "bit_acc": mean("bit_acc"), "clean_bit_acc": mean("clean_bit_acc"),
                      "psnr_object": mean("psnr_object"), "flip_object": mean("flip_object"),
                      "texture_psnr": mean("texture_psnr")}))


if __name__ == "__main__":
    main()
