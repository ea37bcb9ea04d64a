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

The meshes' indices are printed first (`experiments/engines.py --indices` renders the same meshes in
Blender's engines).
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT / "data")
    parser.add_argument("--below", type=float, default=0.75)
    parser.add_argument("--models", nargs="+", default=["default"])
    parser.add_argument("--attacks", default="none,jpeg90,jpeg75,jpeg50,webp80,resize0.5")
    parser.add_argument("--register", action="store_true")
    parser.add_argument("--views", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    sys.path.insert(0, str(ROOT / "experiments"))
    import torch

    from meshseal.api import load
    from meshseal.data.dataset import MeshDataset
    from meshseal.evaluation.attacks import parse
    from meshseal.evaluation.evaluate import evaluate_registered
    from meshseal.threads import configure
    from robust_curve import _Subset

    configure()
    test = MeshDataset(args.data, "test")
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
