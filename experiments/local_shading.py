"""Does a prediction that follows the picture's own low-frequency shading read other engines better?

Detection subtracts the original relit by one fitted point light (`pipeline.relit_residual`); Blender's
shadows, studio light and tone curves are not in it. Here the prediction is multiplied by the ratio
picture / prediction smoothed over the object's pixels (Gaussian, SIGMA picture pixels; the mark's
cells are finer and stay in the residual). For the first N test meshes (the message, views and
settings of `experiments/engines.py`) the marked mesh is rendered by each engine and read with the true
camera, with the plain prediction and with each SIGMA: mean bit accuracy per engine.

    python experiments/local_shading.py --data data --meshes 8 [--engines ours cycles eevee workbench]
        [--sigmas 1.5 3 6]
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

import meshseal
from meshseal import payload, pipeline
from meshseal.distortions import gaussian_blur
from meshseal.mesh import normalize, to_z_up
from meshseal.pipeline import sample_views
from meshseal.render import make_renderer
from engines import BACKGROUND, meshes, png_without_metadata  # experiments/engines.py

PLAIN = pipeline.relit_residual


def shading_following(sigma: float):
    """`relit_residual` whose prediction is scaled by the smoothed picture / prediction ratio."""
    def relit_residual(mesh, image, cameras):
        found = PLAIN(mesh, image, cameras)
        n_images, _, height, width = image.shape
        pixel = found.fragments.pixel.index_select(0, found.keep)
        ratio = ((found.seen + 0.02) / (found.expected + 0.02)).clamp(0.2, 5.0)
        canvas = ratio.new_zeros(n_images * height * width, 3).index_copy(0, pixel, ratio)
        weight = ratio.new_zeros(n_images * height * width, 1).index_copy(0, pixel, torch.ones_like(ratio[:, :1]))
        to_image = lambda flat: flat.reshape(n_images, height, width, -1).permute(0, 3, 1, 2)  # noqa: E731
        smooth = gaussian_blur(to_image(canvas), sigma) / gaussian_blur(to_image(weight), sigma).clamp_min(1e-3)
        factor = smooth.permute(0, 2, 3, 1).reshape(-1, 3).index_select(0, pixel)
        return replace(found, expected=found.expected * factor)
    return relit_residual


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None)
    parser.add_argument("--meshes", type=int, default=8)
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--sampler", default="seed")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--engines", nargs="+", default=["ours", "cycles", "eevee", "workbench"])
    parser.add_argument("--sigmas", nargs="+", type=float, default=[1.5, 3.0, 6.0])
    args = parser.parse_args()
    wm = meshseal.load()
    renderers = {engine: make_renderer(engine) for engine in args.engines}
    variants = {"plain": PLAIN, **{f"sigma {s:g}": shading_following(s) for s in args.sigmas}}
    scores = {(engine, name): [] for engine in args.engines for name in variants}
    for index, (name, mesh) in enumerate(meshes(args)):
        message = f"{index % 10000:04d}"
        marked = wm.embed(mesh, message)
        expected = payload.encode(message, None, wm.n_bits).numpy()
        canonical = normalize(to_z_up(replace(marked, source=None)))
        original = wm.original(mesh)
        cameras, lights = sample_views(args.views, args.sampler, torch.Generator().manual_seed(args.seed * 7919 + index))
        for engine, renderer in renderers.items():
            with torch.no_grad():
                pictures = renderer.render(canonical, cameras, lights, args.size, args.size, background=BACKGROUND)
            for view in range(args.views):
                picture = png_without_metadata(pictures[view, ..., :3].permute(2, 0, 1))
                for variant, function in variants.items():
                    pipeline.relit_residual = function
                    result = wm.decide([wm.read(picture, original, camera=cameras[[view]])])
                    scores[(engine, variant)].append(float(np.mean(np.array([int(b) for b in result.bits]) == expected)))
                pipeline.relit_residual = PLAIN
        print(name, " ".join(f"{e}/{v}={np.mean(s):.3f}" for (e, v), s in scores.items() if s), flush=True)
    print("| engine | " + " | ".join(variants) + " |")
    print("|---|" + "---|" * len(variants))
    for engine in args.engines:
        print(f"| {engine} | " + " | ".join(f"{np.mean(scores[(engine, v)]):.3f}" for v in variants) + " |")


if __name__ == "__main__":
    main()
