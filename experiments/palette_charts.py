"""Palette meshes with and without charts for their palette faces (`methods.charts`), per rendering engine.

For each test mesh that uses its texture as a colour palette (half its textured surface or more on faces
without UV area), a 4-character message is embedded as `meshseal embed` embeds it (palette faces charted
first), and original, charted-but-unmarked and marked meshes are rendered by each engine from 2 seeded
views (256^2, grey background). Per engine and mesh: bit accuracy of the marked pictures saved without
metadata and read with the true camera; the mark's visibility (object PSNR and FLIP, marked against
original); and what charting alone changes (charted-unmarked against original: 'renders as before?').

    python experiments/palette_charts.py --data data [--engines ours eevee workbench cycles] [--meshes N]
        [--without-charts]

`--without-charts` measures the same as before charts existed (palette faces left as they are).
"""

from __future__ import annotations

import argparse
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

import meshseal
from meshseal import payload
from meshseal.api import PALETTE_WARNING
from meshseal.data.dataset import MeshDataset
from meshseal.mesh import normalize, to_z_up
from meshseal.methods import charts
from meshseal.evaluation.metrics import visibility
from meshseal.models.spread import palette_share
from meshseal.render.views import sample_views
from meshseal.render import make_renderer

from engines import BACKGROUND, item_mesh, png_without_metadata  # noqa: E402  (experiments/ on the path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--model", default="default", help="shipped model name or .safetensors path")
    parser.add_argument("--engines", nargs="+", default=["ours", "eevee", "workbench", "cycles"])
    parser.add_argument("--meshes", type=int, default=None, help="at most this many palette meshes")
    parser.add_argument("--without-charts", action="store_true", help="palette faces left as they are (before charts)")
    args = parser.parse_args()
    if args.without_charts:
        charts.CHART_ABOVE = math.inf
    wm = meshseal.load(args.model)
    dataset = MeshDataset(args.data, "test")
    renderers = {engine: make_renderer(engine) for engine in args.engines}
    canonical = lambda mesh: normalize(to_z_up(replace(mesh, source=None)))  # noqa: E731
    rows = {engine: [] for engine in args.engines}
    print("| mesh | engine | bit acc. (2 views, camera known) | marked: object PSNR / FLIP | charted, unmarked: object PSNR / FLIP |")
    print("|---|---|---|---|---|")
    done = 0
    for index in range(len(dataset)):
        item = dataset[index]
        n_verts, n_faces = int(item["n_verts"]), int(item["n_faces"])
        if palette_share(item["positions"][:n_verts], item["faces"][:n_faces], item["uvs"][:n_verts]) < PALETTE_WARNING:
            continue
        if args.meshes is not None and done >= args.meshes:
            break
        done += 1
        mesh = item_mesh(item)
        message = f"{index:04d}"
        expected = payload.encode(message, None, wm.n_bits).numpy()
        marked, original = wm.embed(mesh, message), wm.original(mesh)
        cameras, lights = sample_views(2, "seed", torch.Generator().manual_seed(index))
        for engine, renderer in renderers.items():
            with torch.no_grad():
                pictures = [renderer.render(canonical(m), cameras, lights, 256, 256, background=BACKGROUND)
                            for m in (mesh, wm.layout(mesh), marked)]
            plain, charted, seen = (p[..., :3].permute(0, 3, 1, 2) for p in pictures)
            coverage = pictures[0][..., 3] > 0.5
            mark, layout = visibility(plain, seen, coverage), visibility(plain, charted, coverage)
            bits = [float(np.mean([int(b) for b in wm.decide([wm.read(png_without_metadata(seen[view]), original,
                                                                      camera=cameras[[view]])]).bits] == expected))
                    for view in range(2)]
            rows[engine].append((float(np.mean(bits)), mark, layout))
            print(f"| {item['id']} | {engine} | {np.mean(bits):.3f} | {mark['psnr_object']:.1f} / {mark['flip_object']:.4f} | "
                  f"{layout['psnr_object']:.1f} / {layout['flip_object']:.4f} |", flush=True)
    print("\n| engine | meshes | bit acc. | marked: object PSNR / FLIP | charted, unmarked: object PSNR / FLIP |")
    print("|---|---|---|---|---|")
    for engine, group in rows.items():
        mean = lambda values: float(np.mean(values))  # noqa: E731
        print(f"| {engine} | {len(group)} | {mean([g[0] for g in group]):.3f} | "
              f"{mean([g[1]['psnr_object'] for g in group]):.1f} / {mean([g[1]['flip_object'] for g in group]):.4f} | "
              f"{mean([g[2]['psnr_object'] for g in group]):.1f} / {mean([g[2]['flip_object'] for g in group]):.4f} |")


if __name__ == "__main__":
    main()
