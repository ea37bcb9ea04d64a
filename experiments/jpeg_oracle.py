"""What limits the informed reading after JPEG: the mark, or the prediction? Each picture is read twice
with the camera known: as `meshseal detect` reads it, and by an oracle whose prediction is the true
unmarked picture (the same camera, light and background, 8-bit rounded; then, as in every reading, saved
through the codec found for the picture). The oracle's residual after a codec is exactly what the codec
left of the mark: if it reads far more pictures than the real reading, the prediction (light fit,
footprint, shading) is what to improve; if not, the mark itself is what the codec removes.

    python experiments/jpeg_oracle.py --data data --model robust --meshes 30 [--attacks none,jpeg90,jpeg75,jpeg50,webp80]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

import meshseal
import meshseal.evaluation.evaluate as evaluate_module
import meshseal.methods.spread as spread_module
import meshseal.reading.footprint as footprint_module
from meshseal.data.dataset import MeshDataset
from meshseal.evaluation.attacks import parse
from meshseal.render import MeshRenderer

_clean: list = []  # the last unmarked picture the evaluation rendered (the second render of each mesh)
_real_relit = spread_module.relit_residual


class _Recording(MeshRenderer):
    def __call__(self, *args, **kwargs):
        out = super().__call__(*args, **kwargs)
        _clean[:] = [out.image.clamp(0, 1)]  # the marked picture first, then the clean one: the last stays
        return out


def _oracle_relit(mesh, image, cameras, **kwargs):
    found = _real_relit(mesh, image, cameras, **kwargs)
    clean = torch.round(_clean[0] * 255) / 255
    if clean.shape[-2:] != image.shape[-2:]:  # a resized picture: the clean one resized the same way
        from PIL import Image

        size = (image.shape[-1], image.shape[-2])
        pixels = (clean[0].permute(1, 2, 0).numpy() * 255).round().astype("uint8")
        resized = Image.fromarray(pixels).resize(size, Image.BICUBIC)
        clean = torch.from_numpy(np.asarray(resized).astype("float32") / 255.0).permute(2, 0, 1)[None]
    flat = clean.permute(0, 2, 3, 1).reshape(-1, 3).to(found.expected)
    pixel = found.fragments.pixel.index_select(0, found.keep)
    return replace(found, expected=flat.index_select(0, pixel))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--model", default="robust")
    parser.add_argument("--meshes", type=int, default=30)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--attacks", default="none,jpeg90,jpeg75,jpeg50,webp80")
    args = parser.parse_args()
    attacks = parse(args.attacks)
    dataset = MeshDataset(args.data, "test", seed=0)
    model = meshseal.load(args.model, "cpu").model
    evaluate_module.MeshRenderer = _Recording
    rows = {}
    for reading in ("real", "oracle"):
        started = time.time()
        if reading == "oracle":
            spread_module.relit_residual = _oracle_relit
            spread_module.picture_footprint = lambda *a, **k: None  # the oracle's prediction is already as sampled
            footprint_module.remember_choice = lambda *a, **k: None  # ... so there is no footprint to keep
        rows[reading] = evaluate_module.evaluate_registered(model, dataset, args.meshes, 0, args.size, "seed", None,
                                                            views=1, register=False, max_flip=None, attacks=attacks)
        print(f"<!-- {reading}: {time.time() - started:.0f} s -->", flush=True)
    print(f"`{args.model}`, the first {args.meshes} test meshes, one seeded {args.size}^2 view each, strength 1, "
          "camera known; detected / exact / bit accuracy at FPR 1e-6\n")
    print("| reading | " + " | ".join(attacks) + " |")
    print("|---|" + "---|" * len(attacks))
    for reading, m in rows.items():
        cells = " | ".join(f"{m['attacks'][a]['detected']:.2f} / {m['attacks'][a]['exact']:.2f} / "
                           f"{m['attacks'][a]['bit_acc']:.3f}" for a in attacks)
        print(f"| {reading} | {cells} |")
    print("\nBy kind of picture, detected (`evaluate.picture_kinds`)\n")
    print("| reading | kind | pictures | none | " + " | ".join(attacks) + " |")
    print("|---|---|---|---|" + "---|" * len(attacks))
    for reading, m in rows.items():
        for kind, entry in m.get("by_kind", {}).items():
            cells = " | ".join(f"{entry[a]:.2f}" for a in attacks)
            print(f"| {reading} | {kind} | {entry['pictures']} | {entry['detected_known_camera']:.2f} | {cells} |")


if __name__ == "__main__":
    main()
