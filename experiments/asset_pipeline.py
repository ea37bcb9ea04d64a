"""The asset's road: what an engine import or a re-export does to a marked mesh, then one picture read.

Each mesh (the textured fixtures, and the first N test meshes of --data) is marked as `meshseal embed`
marks it (within the FLIP budget) by each model, then put through one asset attack at a time
(`meshseal.evaluation.asset_attacks`, the suite `meshseal eval --attacks` runs on test meshes): its
textures re-saved as JPEG 90 (Pillow, 4:2:0), halved (bicubic), block-compressed as BC1 or BC7
(`etcpak` to encode, `texture2ddecoder` to decode), the file converted OBJ <-> GLB through trimesh and
read back (`obj_glb`), or decimated to half its faces keeping its UVs (`mesh.simplify`).
The result is rendered by our renderer from one seeded view (256^2, 8-bit) and read against the
unmarked original with the camera known. Reports detected / exact message / named at FPR 1e-6 per step
(named: the owner's test of the message it embedded, `detect --expect-id`, on the same reading), by kind
of asset (fixtures with their own textures; test meshes, whose textures the dataset stores at 128^2).

    pip install etcpak texture2ddecoder
    python experiments/asset_pipeline.py --data data --meshes 40 [--models default robust]
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

import meshseal
from meshseal.data.dataset import MeshDataset
from meshseal.evaluation.asset_attacks import ASSET_ATTACKS, apply
from meshseal.mesh import to_z_up
from meshseal.render import MeshBatch, MeshRenderer
from meshseal.render.views import sample_views
from meshseal.training.finetune import mesh_from_item

FIXTURES = Path(__file__).resolve().parents[1] / "tests" / "fixtures"
FIXTURE_FILES = ["bunny.glb", "suzanne.glb", "multi_material.glb", "teapot/teapot.obj", "sh3d_crate/crate.obj",
                 "sh3d_deckChair/deckChair.obj"]
STEPS = ["none", *ASSET_ATTACKS]


def step(mesh, name):
    return mesh if name == "none" else apply(name, mesh, np.random.default_rng(0))


def _picture(mesh, framed_as, cameras, lights) -> np.ndarray:
    """`mesh` rendered in the canonical frame of `framed_as` (the marked asset before the attack), so
    that an attack that moves the bounding box (decimation) does not move the object in the picture."""
    upright, reference = to_z_up(replace(mesh, source=None)), to_z_up(replace(framed_as, source=None))
    low, high = reference.positions.min(dim=0).values, reference.positions.max(dim=0).values
    scale = (high - low).max().clamp_min(1e-12) / 2.0
    canonical = replace(upright, positions=(upright.positions - (low + high) / 2.0) / scale)
    with torch.no_grad():
        image = MeshRenderer()(MeshBatch.from_mesh(canonical), cameras, lights, 256, 256, (0.5, 0.5, 0.5)).image
    return (image[0].clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None)
    parser.add_argument("--meshes", type=int, default=40)
    parser.add_argument("--models", nargs="+", default=["default", "chroma", "robust"])
    args = parser.parse_args()
    assets = [("fixture", meshseal.load_mesh(FIXTURES / name)) for name in FIXTURE_FILES]
    if args.data is not None:
        dataset = MeshDataset(args.data, "test", seed=0)
        assets += [("test mesh", mesh_from_item(dataset[i])) for i in range(min(args.meshes, len(dataset)))]
    print("| model | assets | " + " | ".join(STEPS) + " |")
    print("|---|---|" + "---|" * len(STEPS))
    for name in args.models:
        watermarker = meshseal.load(name, "cpu")
        counts = {}
        for index, (kind, mesh) in enumerate(assets):
            generator = torch.Generator().manual_seed(index)
            message = int(torch.randint(0, 2 ** 31, (1,), generator=generator))
            marked, _ = watermarker.embed_within(mesh, message)
            original = watermarker.original(mesh)
            cameras, lights = sample_views(1, "seed", generator)
            for what in STEPS:
                tally = counts.setdefault((kind, what), [0, 0, 0, 0])
                tally[0] += 1
                try:
                    picture = _picture(step(marked, what), marked, cameras, lights)
                    reading = watermarker.read(picture, original, camera=cameras)
                except meshseal.MeshsealError:
                    continue
                result = watermarker.decide([reading])
                tally[1] += bool(result.detected)
                tally[2] += result.message == message
                named = watermarker.decide([reading], expect=message)  # the match named it (not a pilot's mark alone)
                tally[3] += bool(named.detected) and named.named is not False
        for kind in ("fixture", "test mesh"):
            if (kind, "none") in counts:
                cells = " | ".join(" / ".join(f"{counts[(kind, s)][i] / counts[(kind, s)][0]:.2f}" for i in (1, 2, 3))
                                   for s in STEPS)
                print(f"| {name} | {counts[(kind, 'none')][0]} {'test meshes' if kind == 'test mesh' else kind + 's'} | {cells} |", flush=True)


if __name__ == "__main__":
    main()
