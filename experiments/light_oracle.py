"""How much of the mark does the informed reading lose to its prediction of the picture? Each test
picture (marked as `meshseal eval` marks it, at strength 1, one seeded 256^2 view of the seed's range,
8-bit) is read with the camera known three ways: as `meshseal detect` reads it (`real`), with the light
fit replaced by the light the picture was rendered with (`truelight`), and with the whole prediction
replaced by the unmarked picture itself (`oracle`: same camera, light and background; saved through the
codec found, as every reading does). Per reading and attack: the mean and median over pictures of the
per-bit z signed by the embedded bit (the mark's strength as the matched filter sees it), and the share
detected at FPR 1e-6. `real` close to `truelight` says the light fit is not what loses the mark;
`truelight` close to `oracle` says the rest of the prediction is not either.

    python experiments/light_oracle.py --data data --model default --meshes 40 [--attacks none,jpeg75,webp80]
        [--readings real,truelight,oracle] [--per-picture]
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

import meshseal
import meshseal.methods.spread as spread_module
import meshseal.reading.footprint as footprint_module
import meshseal.reading.relight as relight_module
import meshseal.render.relight as light_module
from meshseal import payload
from meshseal.api import Watermarker
from meshseal.errors import MeshsealError
from meshseal.data.dataset import MeshDataset, collate
from meshseal.evaluation.attacks import apply as attack, parse
from meshseal.methods.batches import batch_mark_grid, batch_texels_used, charted_item
from meshseal.render import MeshBatch, MeshRenderer, PointLights
from meshseal.render.views import sample_views
from meshseal.training.views import random_backgrounds

_real_relit, _real_fit, _real_footprint = spread_module.relit_residual, light_module.fit_point_light, footprint_module.picture_footprint


def _reading(mode: str, clean: torch.Tensor, lights: PointLights, ambient: float):
    """Patch the reading for `mode` (undone by `_restore`)."""
    if mode == "truelight":  # the light itself, not polished further
        relight_module.POLISH_ITERATIONS = -1
        light_module.fit_point_light = lambda seen, *a, **k: (torch.full((1, 3), ambient, dtype=seen.dtype),
                                                               PointLights(lights.position.to(seen), lights.intensity.to(seen)))
    elif mode == "oracle":
        def oracle(mesh, image, cameras, **kwargs):
            found = _real_relit(mesh, image, cameras, **kwargs)
            flat = clean.permute(0, 2, 3, 1).reshape(-1, 3).to(found.expected)
            return replace(found, expected=flat.index_select(0, found.fragments.pixel.index_select(0, found.keep)))
        spread_module.relit_residual = oracle
        spread_module.picture_footprint = lambda *a, **k: None  # the oracle's prediction is already as sampled


_POLISH = relight_module.POLISH_ITERATIONS


def _restore():
    spread_module.relit_residual, light_module.fit_point_light = _real_relit, _real_fit
    relight_module.POLISH_ITERATIONS = _POLISH
    spread_module.picture_footprint = _real_footprint


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--model", default="default")
    parser.add_argument("--meshes", type=int, default=40)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--attacks", default="none,jpeg75,webp80")
    parser.add_argument("--readings", default="real,truelight,oracle")
    parser.add_argument("--per-picture", action="store_true")
    args = parser.parse_args()
    attacks, readings = parse(args.attacks), args.readings.split(",")
    dataset = MeshDataset(args.data, "test", seed=0)
    model = meshseal.load(args.model, "cpu").model
    model.eval()
    watermarker = Watermarker(model)
    generator = torch.Generator().manual_seed(2_000_003)  # as `meshseal eval` draws them
    renderer = MeshRenderer()
    rows = []
    for index in range(min(args.meshes, len(dataset))):
        batch = charted_item(collate([dataset[index]], "cpu"))
        identity = int(torch.randint(0, 2 ** 31, (1,), generator=generator))
        message = payload.encode(identity, None, model.n_bits)[None]
        positions, normals, uvs, faces, texture = (batch[k] for k in ("positions", "normals", "uvs", "faces", "texture"))
        with torch.no_grad():
            grid = batch_mark_grid(model.texture_encoder, batch)
            marked = model.texture_encoder(texture, message, 1.0, payload.key_seed(None), grid, batch_texels_used(batch))
            cameras, lights = sample_views(1, "seed", generator)
            background = random_backgrounds(1, generator)
            original = MeshBatch.from_tensors(positions, normals, uvs, faces, texture)
            picture = renderer(MeshBatch.from_tensors(positions, normals, uvs, faces, marked), cameras, lights,
                               args.size, args.size, background)
            clean = renderer(original, cameras, lights, args.size, args.size, background)
            pixels = int((clean.rgba[..., 3] > 0.5).sum())
            as_bytes = lambda image: np.round(image.image.clamp(0, 1)[0].permute(1, 2, 0).numpy() * 255).astype(np.uint8)  # noqa: E731
            picture, clean = as_bytes(picture), as_bytes(clean)
        sign = 2.0 * message[0].double() - 1.0
        row = {"mesh": index, "pixels": pixels}
        for number, name in enumerate(attacks):
            rng = np.random.default_rng([0, index, 0, number])
            hit = attack(name, picture, rng) if name != "none" else picture
            for mode in readings:
                _reading(mode, torch.from_numpy(clean.astype(np.float32) / 255).permute(2, 0, 1)[None], lights,
                         float(original.ambient[0, 0]))
                try:
                    reading = watermarker.read(hit.astype(np.float32) / 255, original, camera=cameras)
                    z, _, _ = watermarker.method.soft_bits(reading.evidence[None], None, None)
                    row[(name, mode)] = (float((z * sign).mean()), bool(watermarker.decide([reading]).detected))
                except MeshsealError:
                    row[(name, mode)] = (0.0, False)
                finally:
                    _restore()
        rows.append(row)
        if args.per_picture:
            print(index, pixels, " ".join(f"{a}/{m}={v[0]:.2f}{'*' if v[1] else ''}" for (a, m), v in
                                          ((k, v) for k, v in row.items() if isinstance(k, tuple))), flush=True)
    print(f"`{args.model}`, the first {len(rows)} test meshes, one seeded {args.size}^2 view each, strength 1, camera "
          "known: per-bit z signed by the embedded bit, mean / median over the pictures, and the share detected\n")
    print("| attack | " + " | ".join(readings) + " |")
    print("|---|" + "---|" * len(readings))
    for name in attacks:
        cells = []
        for mode in readings:
            zs, found = [r[(name, mode)][0] for r in rows], [r[(name, mode)][1] for r in rows]
            cells.append(f"{np.mean(zs):.2f} / {np.median(zs):.2f} / {np.mean(found):.2f}")
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
