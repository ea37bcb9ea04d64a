"""A coarser cell grid for minified textures, measured on the test meshes that have one.

Where a texture is minified in a picture, the default's 64^2 cells are under a pixel wide there: the
picture point-samples them (our renderer), averages them (another engine's mipmaps, a resized picture),
or samples them a tenth of a pixel off (a registered camera), and the mark reads only in the first case.
This evaluates models (a shipped name or a `meshseal train` run's model file) on the test meshes whose
64^2 cells are under `--below` px in a standard view (`models.spread.cell_pixels`), each marked as
`meshseal embed` marks (FLIP budget), one seeded 256^2 view each: detected / exact with the camera known
and registered (`--register`), as PNG and after each attack, and the mark's visibility.

    python experiments/minified_grid.py --data data --below 0.75 --models default RUN/model.safetensors
        [--attacks none,jpeg90,jpeg75,jpeg50,webp80,resize0.5] [--register] [--views 1]
    python experiments/minified_grid.py --data data --sheet docs/minified_engines.png --indices 61 60

The meshes' indices are printed first (`experiments/engines.py --indices` renders the same meshes in
Blender's engines). `--sheet OUT.png --indices I ...` draws those test meshes instead, original and marked
(the default, as `embed` marks), in our renderer, Eevee and Cycles (bpy needed), one seeded view each at
256^2, each engine's marked-minus-original difference x8 below (grey: none).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def minified(dataset, below: float, chips: int = 64) -> list[int]:
    """Indices of the test meshes whose `chips`^2 cells are under `below` px in a standard view."""
    from meshseal.data.dataset import collate
    from meshseal.methods.batches import unpadded
    from meshseal.models.spread import cell_pixels

    chosen = []
    for index in range(len(dataset)):
        positions, _, uvs, faces = unpadded(collate([dataset[index]], "cpu"), 0)
        if cell_pixels(positions, faces, uvs, chips) < below:
            chosen.append(index)
    return chosen


def sheet(dataset, indices: list[int], out: Path) -> None:
    """The `--sheet` picture (see the module)."""
    from dataclasses import replace

    import numpy as np
    import torch
    from PIL import Image

    import meshseal
    from engines import BACKGROUND, item_mesh
    from meshseal.mesh import normalize, to_z_up
    from meshseal.render import make_renderer
    from meshseal.render.views import sample_views

    watermarker, rows = meshseal.load("default"), []
    renderers = {engine: make_renderer(engine) for engine in ("ours", "eevee", "cycles")}
    for index in indices:
        mesh = item_mesh(dataset[index])
        pair = [normalize(to_z_up(replace(m, source=None))) for m in (mesh, watermarker.embed(mesh, "0001"))]
        cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(index))
        pictures, differences = [], []
        for renderer in renderers.values():
            original, marked = (renderer.render(m, cameras, lights, 256, 256, background=BACKGROUND)[0, ..., :3] for m in pair)
            pictures += [original, marked]
            differences += [(marked - original) * 8 + 0.5, torch.ones_like(original)]
        rows += [torch.cat(pictures, 1), torch.cat(differences, 1)]
    image = (torch.cat(rows, 0).clamp(0, 1).numpy() * 255).round().astype(np.uint8)
    Image.fromarray(image).save(out)
    print(f"{out}: per mesh, original | marked in ours, Eevee, Cycles; below, marked - original x8")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT / "data")
    parser.add_argument("--below", type=float, default=None, help="px (default: evaluation.evaluate.MINIFIED_BELOW)")
    parser.add_argument("--models", nargs="+", default=["default"])
    parser.add_argument("--attacks", default="none,jpeg90,jpeg75,jpeg50,webp80,resize0.5")
    parser.add_argument("--register", action="store_true")
    parser.add_argument("--views", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sheet", type=Path, default=None)
    parser.add_argument("--indices", type=int, nargs="+", default=[61, 60])
    args = parser.parse_args()
    sys.path.insert(0, str(ROOT / "experiments"))
    import torch

    from meshseal.api import load
    from meshseal.data.dataset import MeshDataset
    from meshseal.evaluation.attacks import parse
    from meshseal.evaluation.evaluate import evaluate_registered
    from meshseal.threads import configure
    from robust_curve import _Subset

    from meshseal.evaluation.evaluate import MINIFIED_BELOW

    configure()
    args.below = MINIFIED_BELOW if args.below is None else args.below
    test = MeshDataset(args.data, "test")
    if args.sheet is not None:
        return sheet(test, args.indices, args.sheet)
    indices = minified(test, args.below)
    print(f"<!-- {len(indices)} test meshes with 64^2 cells under {args.below:g} px: {' '.join(map(str, indices))} -->", flush=True)
    attacks = parse(args.attacks)
    if not args.register:
        attacks = [a for a in attacks if not a.startswith(("resize", "crop", "screenshot"))]  # keep the frame
    print("| model | object FLIP (p95) | " + " | ".join(attacks) + " |")
    print("|---|---|" + "---|" * len(attacks))
    for name in args.models:
        started = time.time()
        torch.manual_seed(0)
        result = evaluate_registered(load(name).model, _Subset(test, indices), len(indices), args.seed, 256, "seed",
                                     None, views=args.views, register=args.register,
                                     attacks=[a for a in attacks if a != "none"])
        rows = {"none": result} | result.get("attacks", {})
        cells = []
        for attack in attacks:
            row = rows[attack]
            if attack == "none":
                known = "" if args.register else "_known_camera"
                detected, exact = row[f"tpr{known}"], row[f"exact_message{known}"]
            else:
                detected, exact = row["detected"], row["exact"]
            cells.append(f"{detected:.2f} / {exact:.2f}")
        print(f"| {name} | {result['flip_object']:.4f} ({result['flip_object_p95']:.4f}) | " + " | ".join(cells) + " |", flush=True)
        print(f"<!-- {name}: {time.time() - started:.0f} s; bit accuracy {result.get('bit_acc', result.get('bit_acc_known_camera')):.3f}; "
              f"registration success {result.get('registration_success', float('nan')):.2f} -->", flush=True)


if __name__ == "__main__":
    main()
