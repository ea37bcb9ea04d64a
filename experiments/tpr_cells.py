"""Which marked pictures go undetected with the camera known, and why: the texture they show.

For test meshes START .. START+N-1: mark the texture with the shipped model (a random 32-bit asset ID,
strength 1, public key), render one seeded 256^2 view of the paper's range (8-bit values, plain random
background), read it with the true camera and decide at FPR 1e-6 (exact null). Prints the undetected
pictures (mesh, p-value, cells of the 128^2 mark grid with evidence, bit accuracy) and the detection
rate by the number of cells the picture shows.

    python experiments/tpr_cells.py --data data [--start 0] [--meshes 100]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

import meshseal
from meshseal import payload
from meshseal.data.dataset import MeshDataset, collate
from meshseal.models.spread import bit_weights, soft_bits
from meshseal.pipeline import random_backgrounds, sample_views, spread_evidence
from meshseal.render import MeshBatch, MeshRenderer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--meshes", type=int, default=100)
    args = parser.parse_args()
    wm = meshseal.load()
    model, key_seed = wm.model, payload.key_seed(None)
    dataset = MeshDataset(args.data, "test")
    generator = torch.Generator().manual_seed(1)
    rows = []
    for index in range(args.start, min(args.start + args.meshes, len(dataset))):
        batch = collate([dataset[index]], "cpu")
        positions, normals, uvs, faces, texture = (batch[k] for k in ("positions", "normals", "uvs", "faces", "texture"))
        asset = int(torch.randint(0, 2 ** 32, (1,), generator=generator))
        raw = payload.encode(payload.Message.id(asset), None, wm.n_bits)[None]
        cameras, lights = sample_views(1, "seed", generator)
        with torch.no_grad():
            marked = MeshBatch.from_tensors(positions, normals, uvs, faces, model.mark_texture(texture, raw, 1.0, key_seed))
            picture = MeshRenderer()(marked, cameras, lights, 256, 256, random_backgrounds(1, generator)).image
            picture = torch.round(picture.clamp(0, 1) * 255) / 255
            evidence = spread_evidence(model, MeshBatch.from_tensors(positions, normals, uvs, faces, texture), picture, cameras)
        z = soft_bits(model.texture_encoder, evidence, key_seed)[0].double()
        p = payload.detection_pvalue(z, bit_weights(model.texture_encoder, evidence, key_seed)[0].double())
        rows.append({"mesh": dataset.rows[index].get("name", str(index)), "p": p, "cells": int((evidence[0] != 0).sum()),
                     "bits": float(((z > 0).double() == raw[0].double()).double().mean())})
    print("| undetected picture | p-value | cells with evidence | bit accuracy |\n|---|---|---|---|")
    for row in sorted((r for r in rows if not payload.detected(r["p"])), key=lambda r: r["cells"]):
        print(f"| {row['mesh']} | {row['p']:.3g} | {row['cells']} | {row['bits']:.3f} |")
    print("\n| cells the picture shows | pictures | detected at FPR 1e-6 |\n|---|---|---|")
    for low, high in ((0, 200), (200, 1000), (1000, 4000), (4000, 10 ** 6)):
        chosen = [payload.detected(r["p"]) for r in rows if low <= r["cells"] < high]
        print(f"| {low}-{high if high < 10 ** 6 else ''} | {len(chosen)} | {np.mean(chosen) if chosen else float('nan'):.2f} |")
    print(f"\nall: {len(rows)} pictures, detected {np.mean([payload.detected(r['p']) for r in rows]):.2f}")


if __name__ == "__main__":
    main()
