"""A sheet to look at: one test mesh (or fixture) rendered original | marked | difference x8 by each
engine, from the same seeded view and light as `experiments/engines.py`; prints each engine's RMS
difference (grey levels over the frame).

    python experiments/engine_pictures.py --data data --index 0 --out docs/engines_bush_shadows.png
        [--engines ours cycles eevee]
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from PIL import Image

import meshseal
from meshseal.mesh import normalize, to_z_up
from meshseal.render.views import sample_views
from meshseal.render import make_renderer
from engines import BACKGROUND, meshes  # experiments/engines.py


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="dataset (its test split); default: the fixtures")
    parser.add_argument("--index", type=int, default=0, help="which mesh, in engines.py's order")
    parser.add_argument("--engines", nargs="+", default=["ours", "cycles", "eevee"])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    args.meshes = args.index + 1
    for index, (name, mesh) in enumerate(meshes(args)):
        if index == args.index:
            break
    wm = meshseal.load()
    marked = wm.embed(mesh, f"{index:04d}")
    canonical = [normalize(to_z_up(replace(m, source=None))) for m in (mesh, marked)]
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(args.seed * 7919 + index))
    rows = []
    for engine in args.engines:
        renderer = make_renderer(engine)
        with torch.no_grad():
            original, watermarked = (renderer.render(m, cameras, lights, args.size, args.size, background=BACKGROUND)[0, ..., :3]
                                     for m in canonical)
        difference = watermarked - original
        print(f"{name} {engine}: RMS difference {float(difference.pow(2).mean().sqrt()) * 255:.3f} grey levels")
        rows.append(torch.cat([original, watermarked, (0.5 + 8 * difference).clamp(0, 1)], 1))
    Image.fromarray((torch.cat(rows, 0).numpy() * 255 + 0.5).astype(np.uint8)).save(args.out)


if __name__ == "__main__":
    main()
