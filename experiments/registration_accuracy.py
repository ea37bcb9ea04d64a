"""How well registration recovers a picture's camera, and what that costs the shipped model's bits.

For each textured fixture: embed a seeded message with the shipped model, render K seeded views at
SIZE^2 with our renderer (8-bit values, plain background, no metadata), then read the bits with the
true camera and with the registered one. Prints, per picture, the pose error (mean pixels between
where the two cameras put the visible surface) after the silhouette stage and after the texture stage, the registration IoU, the bit accuracy either way and the
registration time.

    python experiments/registration_accuracy.py [--views 2] [--size 256] [--fixtures bunny teapot]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import torch

import meshseal
from meshseal import payload
from meshseal.framing import object_mask
from meshseal.mesh import normalize, to_z_up
from meshseal.pipeline import read_bits, sample_views
from meshseal.register import pose_error, refine_on_texture_twice, register
from meshseal.render import MeshBatch, MeshRenderer

FIXTURES = Path(__file__).resolve().parents[1] / "tests" / "fixtures"
TEXTURED = {"bunny": "bunny.glb", "teapot": "teapot/teapot.obj", "crate": "sh3d_crate/crate.obj",
            "deckChair": "sh3d_deckChair/deckChair.obj", "suzanne": "suzanne.glb", "multi_material": "multi_material.glb"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--fixtures", nargs="*", default=list(TEXTURED))
    args = parser.parse_args()
    torch.manual_seed(0)
    wm = meshseal.load()
    seed = payload.key_seed(None)  # embed marks with the public key's pattern
    rows = []
    for name in args.fixtures:
        mesh = meshseal.load_mesh(FIXTURES / TEXTURED[name])
        bits = torch.randint(0, 2, (wm.n_bits,), generator=torch.Generator().manual_seed(len(name))).tolist()
        marked = wm.embed(mesh, bits)
        original = wm.original(mesh)
        marked_batch = MeshBatch.from_mesh(normalize(to_z_up(replace(marked, source=None))))
        cameras, lights = sample_views(args.views, "seed", torch.Generator().manual_seed(args.seed))
        with torch.no_grad():
            pictures = MeshRenderer()(marked_batch, cameras, lights, args.size, args.size).image
        pictures = torch.round(pictures.clamp(0, 1) * 255) / 255
        truth = torch.tensor(bits, dtype=torch.float32)
        for view in range(args.views):
            picture = pictures[view]
            known = read_bits(wm.model, original, picture[None], cameras[[view]], seed)[0]
            mask, background = object_mask(picture.permute(1, 2, 0).numpy())
            start = time.perf_counter()
            found = register(original, picture, torch.from_numpy(mask), torch.tensor(background, dtype=torch.float32),
                             texture_refine=False)
            silhouette_error = pose_error(original, cameras[[view]], found.camera, args.size, args.size)
            found.camera = refine_on_texture_twice(original, found.camera, picture[None], torch.from_numpy(mask)[None].float())
            seconds = time.perf_counter() - start
            registered = read_bits(wm.model, original, picture[None], found.camera, seed)[0]
            error = pose_error(original, cameras[[view]], found.camera, args.size, args.size)
            row = (name, view, error, found.iou, float(((known > 0).float() == truth).float().mean()),
                   float(((registered > 0).float() == truth).float().mean()), seconds)
            rows.append(row)
            print(f"{name:15s} view {view}: reprojection {silhouette_error:6.2f} -> {error:6.2f} px  IoU {found.iou:.3f}  "
                  f"bits known {row[4]:.3f}  registered {row[5]:.3f}  {seconds:.1f} s", flush=True)
    n = len(rows)
    print(f"mean: reprojection {sum(r[2] for r in rows) / n:.2f} px, success (< 0.5 px) "
          f"{sum(r[2] < 0.5 for r in rows) / n:.2f}, bits known {sum(r[4] for r in rows) / n:.4f}, "
          f"registered {sum(r[5] for r in rows) / n:.4f}, {sum(r[6] for r in rows) / n:.2f} s per picture")


if __name__ == "__main__":
    main()
