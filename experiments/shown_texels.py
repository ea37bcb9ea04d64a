"""Where the mark's energy goes: over the whole texture, or over the texels the mesh shows.

The shipped mark scales its residual to the target texture PSNR. Normalised over the whole texture
(as before), a mesh that shows a small part of its texture gets most of the energy on texels no view
sees, and one whose shown part is busy gets more than the target there; normalised over the texels
the mesh shows (`models.spread.texels_used`, now shipped), the PSNR over those is the target for
every mesh. For every test mesh, marked as `meshseal embed` marks it (its cell grid, an error-
corrected ID) and rendered from two seed views (256^2, 8-bit, plain random background, as the model
card's camera-known row), read with the camera known: bit accuracy, detection at FPR 1e-6, texture
PSNR over the whole texture and over the shown texels (mean, 10th percentile, minimum), object-pixel
PSNR and FLIP; split into meshes with a UV map and those that use the texture as a colour palette
(half their surface or more on faces without UV area, `models.spread.palette_share`). `--floor`
changes the activity mask's floor.

    python experiments/shown_texels.py --data data --normalise whole
    python experiments/shown_texels.py --data data --normalise shown [--floor 1.0]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

import meshseal
from meshseal import payload
from meshseal.api import PALETTE_WARNING
from meshseal.data.dataset import MeshDataset, collate
from meshseal.metrics import shown_texture_psnr, visibility
from meshseal.models.spread import palette_share
from meshseal.pipeline import batch_mark_grid, batch_texels_used, random_backgrounds, sample_views
from meshseal.render import MeshBatch, MeshRenderer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--normalise", choices=("whole", "shown"), default="shown")
    parser.add_argument("--floor", type=float, default=None, help="the activity mask's floor (default the model's)")
    parser.add_argument("--meshes", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jsonl", type=Path, default=None, help="also write one line per picture here")
    args = parser.parse_args()
    wm = meshseal.load()
    model, encoder = wm.model, wm.model.texture_encoder
    if args.floor is not None:
        encoder.floor = args.floor
    dataset = MeshDataset(args.data, "test")
    count = len(dataset) if args.meshes is None else min(args.meshes, len(dataset))
    generator = torch.Generator().manual_seed(args.seed + 2_000_003)  # the model card's draws
    renderer, rows = MeshRenderer(), []
    for index in range(count):
        batch = collate([dataset[index]], "cpu")
        positions, normals, uvs, faces, texture = (batch[k] for k in ("positions", "normals", "uvs", "faces", "texture"))
        identity = int(torch.randint(0, 2 ** 31, (1,), generator=generator))
        message = payload.encode(identity, None, model.n_bits)[None]
        shown = batch_texels_used(batch)
        with torch.no_grad():
            marked = model.mark_texture(texture, message, 1.0, payload.key_seed(None), batch_mark_grid(model, batch),
                                        shown if args.normalise == "shown" else None)
            cameras, lights = sample_views(2, "seed", generator)
            background = random_backgrounds(2, generator)
            renders = [renderer(MeshBatch.from_tensors(positions, normals, uvs, faces, t), cameras, lights, 256, 256, background)
                       for t in (texture, marked)]
        pictures = torch.round(renders[1].image.clamp(0, 1) * 255) / 255
        original = MeshBatch.from_tensors(positions, normals, uvs, faces, texture)
        n_verts, n_faces = int(batch["n_verts"][0]), int(batch["n_faces"][0])
        palette = palette_share(positions[0, :n_verts], faces[0, :n_faces], uvs[0, :n_verts]) >= PALETTE_WARNING
        whole = float(shown_texture_psnr(marked, texture, torch.ones_like(shown))[0])
        on_shown = float(shown_texture_psnr(marked, texture, shown)[0])
        for view in range(2):
            seen = visibility(renders[0].image[[view]], renders[1].image[[view]], renders[1].rgba[[view], ..., 3] > 0.5)
            try:
                decision = wm.decide([wm.read(pictures[view].permute(1, 2, 0).numpy(), original, camera=cameras[[view]])])
                accuracy = float(np.mean([int(b) for b in decision.bits] == message[0].numpy()))
                detected = bool(decision.detected)
            except meshseal.MeshsealError:  # nothing to read: chance
                accuracy, detected = 0.5, False
            rows.append({"mesh": index, "view": view, "bit_acc": accuracy, "detected": detected, "palette": palette,
                         "psnr_texture": whole, "psnr_texture_shown": on_shown, "psnr_object": seen["psnr_object"],
                         "flip_object": seen["flip_object"]})
            if args.jsonl is not None:
                with args.jsonl.open("a") as out:
                    out.write(json.dumps(rows[-1]) + "\n")
        if (index + 1) % 50 == 0:
            print(f"{index + 1}/{count} meshes", flush=True)
    column = lambda key, part: np.array([r[key] for r in part], dtype=float)  # noqa: E731
    print(f"normalised over the {args.normalise} texture{'' if args.normalise == 'whole' else ' texels'}, floor {encoder.floor}")
    print("| pictures | n | bit acc. | detected | texture PSNR | shown-texel PSNR: mean / p10 / min | object PSNR | object FLIP |")
    print("|---|---|---|---|---|---|---|---|")
    for name, part in (("all", rows), ("UV-mapped", [r for r in rows if not r["palette"]]),
                       ("palette", [r for r in rows if r["palette"]])):
        if not part:
            continue
        shown_psnr, object_psnr = column("psnr_texture_shown", part), column("psnr_object", part)
        print(f"| {name} | {len(part)} | {column('bit_acc', part).mean():.4f} | {column('detected', part).mean():.3f} | "
              f"{column('psnr_texture', part).mean():.2f} | {shown_psnr.mean():.2f} / {np.quantile(shown_psnr, 0.1):.2f} / "
              f"{shown_psnr.min():.2f} | {object_psnr[np.isfinite(object_psnr)].mean():.2f} | "
              f"{column('flip_object', part).mean():.4f} |")


if __name__ == "__main__":
    main()
