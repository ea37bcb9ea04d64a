"""False positives after the web's attacks: unmarked test meshes, rendered from seeded views, saved as
8-bit PNG, put through each attack (an asset attack of `meshseal.evaluation.asset_attacks`, such as
`texture_half`: on the unmarked mesh before its picture) and read with the camera known (or, `--register`, without it) by a spread model (default: `robust`,
whose reading picks the picture's codec). Without a mark the detection p-values must be uniform or
larger: reports per attack the pictures, how many reach the FPR 1e-6 threshold, the smallest p-value,
the share under 0.01 and 0.1, and a Kolmogorov-Smirnov p-value against uniform.

    python experiments/robust_null.py --data data --meshes 200 [--start 0] [--views 1] [--model robust] [--json OUT] [--register]
        [--fine-grid]   (only the meshes read on the model's fine grid: magnified textures)
        [--light-gain G]  (pictures lit G times as strongly: highlights that clip)
    python experiments/robust_null.py --merge A.json B.json ...   # one table over runs' --json files (e.g. halves of the split)
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from scipy import stats

import meshseal
from meshseal import payload
from meshseal.data.dataset import MeshDataset, collate
from meshseal.evaluation.asset_attacks import ASSET_ATTACKS
from meshseal.evaluation.asset_attacks import apply as attack_asset
from meshseal.evaluation.attacks import apply, parse
from meshseal.mesh import Material, Mesh
from meshseal.methods.batches import charted_item
from meshseal.render import MeshBatch, MeshRenderer
from meshseal.render.views import sample_views
from meshseal.training.views import random_backgrounds


def table(p_values: dict[str, list[float]]) -> None:
    """The Markdown table of p-values per attack, and a last row over every picture."""
    print("| attack | pictures | at FPR 1e-6 | smallest p | p < 0.01 | p < 0.1 | KS p (uniform) |")
    print("|---|---|---|---|---|---|---|")
    rows = [*p_values.items(), ("all", [v for values in p_values.values() for v in values])]
    for name, values in rows:
        values = np.array(values)
        if len(values) == 0:  # no picture read (say, no mesh of --fine-grid among those given)
            print(f"| {name} | 0 | - | - | - | - | - |")
            continue
        print(f"| {name} | {len(values)} | {int((values <= payload.FPR).sum())} | {values.min():.2g} | "
              f"{(values < 0.01).mean():.3f} | {(values < 0.1).mean():.3f} | {stats.kstest(values, 'uniform').pvalue:.2g} |")


def merge(paths: list[Path]) -> None:
    """One table over several runs' `--json` files (their p-values per attack put together)."""
    p_values: dict[str, list[float]] = {}
    runs = [json.loads(path.read_text()) for path in paths]
    for run in runs:
        for name, values in run["p_values"].items():
            p_values.setdefault(name, []).extend(values)
    models = sorted({run["model"] for run in runs})
    print(f"{', '.join(models)}: {len(runs)} runs put together ({', '.join(str(p) for p in paths)})\n")
    table(p_values)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--merge", type=Path, nargs="+", help="print one table over these runs' --json files, and stop")
    parser.add_argument("--data", type=Path)
    parser.add_argument("--meshes", type=int, default=200)
    parser.add_argument("--start", type=int, default=0, help="the first test mesh (runs can share the split)")
    parser.add_argument("--views", type=int, default=1)
    parser.add_argument("--model", default="robust")
    parser.add_argument("--attacks", default="none,jpeg95,jpeg90,jpeg75,jpeg50,webp80,brightness,noise2")
    parser.add_argument("--json", type=Path, help="also write every p-value here (per attack)")
    parser.add_argument("--fine-grid", action="store_true",
                        help="only the meshes whose reading takes the model's fine grid (magnified textures)")
    parser.add_argument("--register", action="store_true",
                        help="read without the camera, as `meshseal detect` reads a picture without metadata")
    parser.add_argument("--light-gain", type=float, default=1.0,
                        help="light the pictures this many times as strongly as the seed's lights (highlights that clip)")
    args = parser.parse_args()
    if args.merge:
        merge(args.merge)
        return
    if args.data is None:
        parser.error("--data is required (or --merge)")
    watermarker = meshseal.load(args.model, "cpu")
    attacks = parse(args.attacks)
    dataset = MeshDataset(args.data, "test", seed=0)
    generator, rng = torch.Generator().manual_seed(7), np.random.default_rng(7)
    p_values = {name: [] for name in attacks}
    started = time.time()
    for index in range(args.start, min(args.start + args.meshes, len(dataset))):
        batch = charted_item(collate([dataset[index]], "cpu"))
        original = MeshBatch.from_tensors(*(batch[k] for k in ("positions", "normals", "uvs", "faces", "texture")))
        cameras, lights = sample_views(args.views, "seed", generator)
        lights = type(lights)(lights.position, lights.intensity * args.light_gain)
        backgrounds = random_backgrounds(args.views, generator)
        if args.fine_grid and watermarker.method.encoder.fine_chips not in watermarker.method.grids_to_read(
                watermarker.original(original)):
            if (index + 1 - args.start) % 25 == 0:
                print(f"{index + 1} meshes looked at, {sum(map(len, p_values.values()))} pictures, "
                      f"{time.time() - started:.0f} s", file=sys.stderr, flush=True)
            continue
        as_bytes = lambda image: (image.clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)  # noqa: E731
        with torch.no_grad():
            pictures = MeshRenderer()(original, cameras, lights, 256, 256, backgrounds).image
            assets = {}  # the pictures of each asset attack's mesh, in the same views
            mesh = Mesh(batch["positions"][0], batch["normals"][0], batch["faces"][0], batch["uvs"][0],
                        materials=[Material(texture=batch["texture"][0].permute(1, 2, 0))])
            for name in (n for n in attacks if n in ASSET_ATTACKS):
                hit = MeshBatch.from_mesh(attack_asset(name, mesh, rng))
                assets[name] = MeshRenderer()(hit, cameras, lights, 256, 256, backgrounds).image
        for view in range(args.views):
            clean = as_bytes(pictures[view])
            for name in attacks:
                picture = as_bytes(assets[name][view]) if name in assets else apply(name, clean, rng)
                try:
                    if args.register:
                        reading = watermarker.read(picture, original, register=True)
                        reading = watermarker.look_again(reading, original)
                    else:
                        reading = watermarker.read(picture, original, camera=cameras[[view]])
                except meshseal.MeshsealError:
                    continue
                p_values[name].append(watermarker.decide([reading]).p_value)
        if (index + 1 - args.start) % 25 == 0:
            print(f"{index + 1} meshes, {sum(map(len, p_values.values()))} pictures, {time.time() - started:.0f} s",
                  file=sys.stderr, flush=True)
    print(f"{args.model}: unmarked test meshes, {args.views} view(s) each, "
          f"{'registered' if args.register else 'camera known'}, "
          f"{time.time() - started:.0f} s\n")
    table(p_values)
    if args.json:
        args.json.write_text(json.dumps({"model": args.model, "views": args.views, "p_values": p_values}))


if __name__ == "__main__":
    main()
