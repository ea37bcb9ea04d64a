"""How big a mark cell is in a picture, and what coarser cells do where it is small.

For each of the first N test meshes: the size in pixels of one of the shipped mark's cells (the UV
square cut into `chips` x `chips`) on the object, for our standard view of a 256^2 picture (the object
normalised to its bounding sphere, seen from 3.5 radii with a 60-degree field): the area-weighted median
over textured faces of sqrt(world area / UV area), divided by the cell count and the pixel's size
there. With `--read`, the meshes whose cells are smaller than `--below` pixels (or, with `--above`,
larger than that many) are marked with each of `--chips` cell grids (everything else as shipped,
texture PSNR 40 dB; a texture with fewer texels than a grid has cells resampled up), rendered as
experiments/registration_conditions.py renders "plain" (one seeded view, a plain background, PNG, no
metadata), and read with the true camera and registered (on that grid alone); visibility is over the
object's pixels. (This measured the case for `coarse_chips` and `fine_chips`: the shipped model now
marks such meshes on 64^2 and 512^2 cells itself.)

    python experiments/chip_footprint.py --data data --meshes 100 [--read --below 0.6 --chips 128 64 32]
    python experiments/chip_footprint.py --data data --meshes 100 --read --above 2.0 --chips 128 256 512
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import numpy as np
import torch

import meshseal
from meshseal import payload
from meshseal.data.dataset import MeshDataset, collate
from meshseal.evaluation.metrics import visibility
from meshseal.models.spread import SpreadSpectrumEncoder, cell_pixels
from meshseal.training.views import random_backgrounds
from meshseal.render.views import sample_views
from meshseal.reading.registration import pose_error
from meshseal.render import MeshBatch, MeshRenderer



def cell_size(item: dict, chips: int) -> float:
    n_verts, n_faces = int(item["n_verts"]), int(item["n_faces"])
    return cell_pixels(item["positions"][:n_verts], item["faces"][:n_faces], item["uvs"][:n_verts], chips)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--meshes", type=int, default=100)
    parser.add_argument("--read", action="store_true", help="mark and read the meshes with small cells")
    parser.add_argument("--below", type=float, default=0.6, help="cell size (pixels) under which a mesh is read")
    parser.add_argument("--above", type=float, default=None, help="read the meshes with cells over this many pixels instead")
    parser.add_argument("--chips", type=int, nargs="+", default=[128, 64, 32])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--model", default="chroma", help="shipped model whose mark colour and reading settings the "
                        "grids use (the grid choice was measured with `chroma`)")
    args = parser.parse_args()
    wm = meshseal.load(args.model)
    shipped = wm.model.texture_encoder
    dataset = MeshDataset(args.data, "test")
    count = min(args.meshes, len(dataset))
    sizes = [cell_size(dataset[index], shipped.chips) for index in range(count)]
    print(f"cell size at {shipped.chips}^2 cells, 256^2 pictures: median {statistics.median(sizes):.2f} px; "
          + ", ".join(f"under {edge}: {sum(s < edge for s in sizes)}" for edge in (0.3, 0.6, 1.0)) + f" of {count}")
    if not args.read:
        return
    if args.above is None:
        small, which = [index for index in range(count) if sizes[index] < args.below], f"under {args.below}"
    else:
        small, which = [index for index in range(count) if sizes[index] > args.above], f"over {args.above}"
    renderer = MeshRenderer()
    print(f"{len(small)} meshes with cells {which} px: {small}")
    print("| cells | meshes | object PSNR | object FLIP | bits, true camera | bits, registered | registration < 0.5 px | detected (FPR 1e-6) |")
    print("|---|---|---|---|---|---|---|---|")
    for chips in args.chips:
        wm.model.texture_encoder = SpreadSpectrumEncoder(shipped.n_bits, chips, wm.model.config.mark_colour, shipped.texture_psnr,
                                                         shipped.window, shipped.floor, shipped.seed)
        rows = []
        for index in small:
            batch = collate([dataset[index]], "cpu")
            positions, normals, uvs, faces, texture = (batch[k] for k in ("positions", "normals", "uvs", "faces", "texture"))
            original = MeshBatch.from_tensors(positions, normals, uvs, faces, texture)
            generator = torch.Generator().manual_seed(args.seed * 100003 + index)
            identity = int(torch.randint(0, 2 ** 31, (1,), generator=generator))
            message = payload.encode(identity, None, wm.model.n_bits)[None]
            with torch.no_grad():
                marked = wm.model.texture_encoder(texture, message, 1.0, payload.key_seed(None))
                cameras, lights = sample_views(1, "seed", generator)
                renders = [renderer(MeshBatch.from_tensors(positions, normals, uvs, faces, t), cameras, lights, 256, 256,
                                    torch.zeros(1, 3)) for t in (texture, marked)]
                alpha = renders[1].rgba[0, ..., 3][None]
                picture = (renders[1].image[0] + (1 - alpha) * random_backgrounds(1, generator)[0][:, None, None].expand(3, 256, 256)).clamp(0, 1)
                seen = visibility(renders[0].image, renders[1].image, alpha > 0.5)
            pixels = (picture.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8).astype(np.float32) / 255
            agree = lambda r: float(np.mean([int(b) for b in wm.decide([r]).bits] == message[0].numpy()))  # noqa: E731
            readings = []
            for how in ({"camera": cameras}, {"register": True}):
                try:
                    readings.append(wm.read(pixels, original, **how))
                except meshseal.MeshsealError:  # no object found: read at chance
                    readings.append(None)
            known, reading = readings
            rows.append({"psnr": seen["psnr_object"], "flip": seen["flip_object"], "known": 0.5 if known is None else agree(known),
                         "registered": 0.5 if reading is None else agree(reading),
                         "pose": float("inf") if reading is None else pose_error(original, cameras, reading.found, 256, 256),
                         "detected": reading is not None and bool(wm.decide([reading]).detected)})
            print(f"  {chips} mesh {index}: cells {sizes[index] * shipped.chips / chips:.2f} px, bits known "
                  f"{rows[-1]['known']:.3f} registered {rows[-1]['registered']:.3f}, FLIP {rows[-1]['flip']:.4f}", flush=True)
        mean = lambda key: float(np.mean([r[key] for r in rows]))  # noqa: E731
        print(f"| {chips}^2 | {len(rows)} | {mean('psnr'):.2f} | {mean('flip'):.4f} | {mean('known'):.3f} | "
              f"{mean('registered'):.3f} | {np.mean([r['pose'] < 0.5 for r in rows]):.2f} | {mean('detected'):.2f} |", flush=True)


if __name__ == "__main__":
    main()
