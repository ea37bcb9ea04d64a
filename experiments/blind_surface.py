"""The blind surface-code model (`models/surface.py`, shipped as `blind` and `blind8`), measured step by
step in the seed paper's protocol: the test items with spherical UVs and a noise or real texture (what
`meshseal eval --protocol seed` reads), the seed's camera and light ranges, 600 x 400 pictures by our
renderer, read from the picture alone. Each flag turns one of the shipped model's steps back into what
was tried first, so that the table in docs/mark.md comes from this one command:

python experiments/blind_surface.py --data data --bits 8 --cells 32 --psnr 28 [--uv-only] [--isotropic 2]
    [--floor 0.3] [--pool 1] [--codes sequency] [--host-free] [--stretches 0.95 1 1.05] [--sphere]

--uv-only: each texel's column from the UV map alone (the outermost point where several share it), not
from the points the seed's views show; --isotropic S: the picture's chroma high-passed by an isotropic
Gaussian of S pixels (`whiten` below) instead of along rows; --pool P: a cell's evidence
is its sum over count^P; --codes sequency: the Walsh functions with the fewest sign changes, unscrambled;
--host-free: read the difference between the marked and the original picture (what the host texture
costs); --sphere: a UV sphere with noise textures; --own: the test items with their own UV atlases; --split
train: the training meshes (to tune without the test split). Each run also splits the accuracy by how much
the texels a picture shows are shared between places of the object, and by the object's width in pixels.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

import meshseal.models.surface as surface
from meshseal.mesh import spherical_uv
from meshseal.evaluation.metrics import visibility
from meshseal.render import MeshBatch, MeshRenderer, sample_seed_cameras, sample_seed_lights
from meshseal.reading.framing import object_mask
from meshseal.models.surface import SurfaceCodeEncoder, read_picture, reference_columns, texel_columns


def whiten(image: np.ndarray, mask: np.ndarray, colour: np.ndarray, sigma: float = 2.0) -> np.ndarray:
    """The picture's chroma along the mark's colour, minus its local mean, over its local RMS: shading
    and smooth host texture drop out, busy and dark regions count alike. (H, W, 3) -> (H, W), 0 off
    the object."""
    from scipy import ndimage

    signal = image @ colour
    weight = ndimage.gaussian_filter(mask.astype(float), sigma) + 1e-6
    mean = ndimage.gaussian_filter(signal * mask, sigma) / weight
    detail = (signal - mean) * mask
    energy = ndimage.gaussian_filter(detail * detail, 3 * sigma) / ndimage.gaussian_filter(mask.astype(float), 3 * sigma).clip(1e-6)
    return np.where(mask, detail / np.sqrt(energy + 1e-8), 0.0)


def sphere_items(count: int):
    """A UV sphere (icosphere, spherical UVs) with a different seed-style noise texture each time: the
    shape spherical UVs suit best, to tell the code's limits from the mapping's."""
    import trimesh

    from meshseal.data.process import noise_texture

    sphere = trimesh.creation.icosphere(5)
    positions = torch.tensor(sphere.vertices, dtype=torch.float32)
    for index in range(count):
        texture = torch.tensor(noise_texture(np.random.default_rng(index), 128)).permute(2, 0, 1).float() / 255
        yield {"id": f"sphere-{index}", "positions": positions, "uvs": spherical_uv(positions), "texture": texture,
               "normals": torch.tensor(sphere.vertex_normals, dtype=torch.float32), "faces": torch.tensor(sphere.faces)}


def render_pair(item: dict, texture: torch.Tensor, marked: torch.Tensor, generator: torch.Generator,
                height: int, width: int):
    """The original and the marked `item` rendered from one seed-range camera and light drawn from
    `generator`, as 8-bit pictures (H, W, 3), and the mark's visibility over the object's pixels."""
    cameras, lights = sample_seed_cameras(1, generator), sample_seed_lights(1, generator)
    renderer, pictures = MeshRenderer(), []
    for tex in (texture, marked):
        batch = MeshBatch.from_tensors(item["positions"][None], item["normals"][None], item["uvs"][None],
                                       item["faces"], tex)
        with torch.no_grad():
            pictures.append(renderer(batch, cameras, lights, height, width).rgba[0])
    original, picture = (torch.round(p[..., :3].clamp(0, 1) * 255) / 255 for p in pictures)
    coverage = pictures[0][..., 3] > 0.5
    return original, picture, visibility(original.permute(2, 0, 1)[None], picture.permute(2, 0, 1)[None],
                                          coverage[None])


def uv_only_columns(positions, normals, faces, uvs, height, width):
    """`texel_columns` without the seed's views: the point the UV map puts each texel on."""
    points, painted = surface._uv_raster(positions.float(), faces.long(), uvs.float(), height, width)
    return reference_columns(points, positions.float()), painted


def shared_texels(positions, normals, faces, uvs, height, width) -> float:
    """How much the texels the seed's views show disagree on their column: the mean, over the object's
    seen pixels, of |column - the mean column of the texel it shows| (0: every texel paints one place)."""
    column, index = surface.seen_texels(positions, normals, faces, uvs, height, width)
    total = torch.zeros(height * width, dtype=torch.float64).index_add_(0, index, column)
    count = torch.zeros(height * width, dtype=torch.float64).index_add_(0, index, torch.ones_like(column))
    return float((column - (total / count.clamp_min(1.0))[index]).abs().mean())


def read_isotropic(encoder: SurfaceCodeEncoder, image: np.ndarray, mask: np.ndarray, sigma: float) -> torch.Tensor:
    """`read_picture` with an isotropic whitening (`whiten`) instead of the row high-pass."""
    return read_picture(encoder, image, mask, whiten(image, mask, encoder.colour.numpy().astype(np.float64), sigma))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="data")
    parser.add_argument("--meshes", type=int, default=97)
    parser.add_argument("--bits", type=int, default=8)
    parser.add_argument("--cells", type=int, default=32)
    parser.add_argument("--psnr", type=float, default=28.0, help="texture PSNR over the painted texels")
    parser.add_argument("--floor", type=float, default=3.0, help="the activity mask's floor")
    parser.add_argument("--pool", type=float, default=surface.POOL)
    parser.add_argument("--uv-only", action="store_true")
    parser.add_argument("--isotropic", type=float, default=0.0)
    parser.add_argument("--codes", choices=("scrambled", "sequency"), default="scrambled")
    parser.add_argument("--host-free", action="store_true")
    parser.add_argument("--sphere", action="store_true")
    parser.add_argument("--own", action="store_true", help="the test items with their own UV atlases instead")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--split", default="test", help="the dataset split (train: to tune without the test meshes)")
    args = parser.parse_args()

    surface.POOL = args.pool
    encoder = SurfaceCodeEncoder(args.bits, args.cells, texture_psnr=args.psnr, floor=args.floor)
    if args.codes == "sequency":  # the Walsh functions of fewest sign changes: a shift of a cell costs little
        walsh = surface._hadamard(args.cells)
        walsh = walsh[np.argsort((np.diff(walsh, axis=1) != 0).sum(1), kind="stable")]
        encoder.codes = torch.tensor(walsh[1:args.bits + 1], dtype=torch.float32)
    columns_of = uv_only_columns if args.uv_only else texel_columns
    generator = torch.Generator().manual_seed(args.seed)
    if args.sphere:
        items = sphere_items(args.meshes)
    else:
        from meshseal.data.dataset import MeshDataset

        kinds = ("own",) if args.own else ("noise", "real")
        dataset = MeshDataset(args.data, args.split, seed=args.seed, texture_kinds=kinds)
        items = (dataset[i] for i in range(min(args.meshes, len(dataset))))
    rows = []
    for item in items:
        message = torch.randint(0, 2, (1, args.bits), generator=generator).float()
        texture = item["texture"][None]
        n_verts = int(item.get("n_verts", len(item["positions"])))
        n_faces = int(item.get("n_faces", len(item["faces"])))
        positions, normals, uvs = item["positions"][:n_verts], item["normals"][:n_verts], item["uvs"][:n_verts]
        columns, painted = columns_of(positions, normals, item["faces"][:n_faces], uvs, *texture.shape[-2:])
        with torch.no_grad():
            marked = encoder(texture, message, columns[None], painted[None])
        original, picture, seen = render_pair(item, texture, marked, generator, *surface.VIEW_SIZE)
        started = time.perf_counter()
        image = picture.numpy().astype(np.float64)
        mask, _ = object_mask(image)
        if args.host_free:
            image = image - original.numpy() + 0.5
        read = (lambda x: read_isotropic(encoder, x, mask, args.isotropic)) if args.isotropic else \
            (lambda x: read_picture(encoder, x, mask))
        soft, clean = read(image), read(original.numpy().astype(np.float64))
        truth = message[0].bool()
        row = {"mesh": item["id"], "bit_acc": float(((soft > 0) == truth).float().mean()),
               "shared": shared_texels(positions, normals, item["faces"][:n_faces], uvs, *texture.shape[-2:]),
               "clean_bit_acc": float(((clean > 0) == truth).float().mean()),
               "width_px": int(np.ptp(np.nonzero(mask)[1]) + 1) if mask.any() else 0,
               "texture_psnr_painted": float(-10 * torch.log10((marked - texture).pow(2).mean(1)[0][painted].mean())),
               "seconds": time.perf_counter() - started, **seen}
        rows.append(row)
        print(f"{item['id'][:36]:36s} bits {row['bit_acc']:.3f} (unmarked {row['clean_bit_acc']:.3f}) object PSNR "
              f"{seen['psnr_object']:.2f} FLIP {seen['flip_object']:.4f}", flush=True)
    mean = lambda key, part=rows: float(np.mean([r[key] for r in part]))  # noqa: E731
    for low, high in ((0.0, 0.01), (0.01, 0.03), (0.03, 0.1), (0.1, 1.0)):  # by how much texels are shared
        part = [r for r in rows if low <= r["shared"] < high]
        if part:
            print(f"texels shared {low:.2f}-{high:.2f} of the object's width: {len(part)} meshes, bit accuracy "
                  f"{mean('bit_acc', part):.3f}")
    for low, high in ((0, 64), (64, 128), (128, 200), (200, 10_000)):  # by the object's width in the picture
        part = [r for r in rows if low <= r["width_px"] < high]
        if part:
            print(f"object {low}-{high} px wide: {len(part)} pictures, bit accuracy {mean('bit_acc', part):.3f}")
    print(json.dumps({"bits": args.bits, "cells": args.cells, "meshes": len(rows), "bit_acc": round(mean("bit_acc"), 4),
                      "clean_bit_acc": round(mean("clean_bit_acc"), 4), "psnr_object": round(mean("psnr_object"), 2),
                      "flip_object": round(mean("flip_object"), 4),
                      "texture_psnr_painted": round(mean("texture_psnr_painted"), 2)}))


if __name__ == "__main__":
    main()
