"""Detection on pictures from another renderer (OpenGL through moderngl/EGL) with the camera unknown.

Each fixture is watermarked with a random message, rendered by the OpenGL reference renderer from
seeded views of the seed's range (and lights), saved as 8-bit PNGs *without* camera metadata, and
read back with `Watermarker.detect(..., register=True)` against the original mesh. Prints per-picture
bit accuracy and registration IoU, and the mean.

    python experiments/detect_other_renderer.py [--model default] [--views 2] [--size 256]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch
from PIL import Image

import meshseal
from meshseal.mesh import normalize, to_z_up
from meshseal.render import sample_seed_cameras, sample_seed_lights
from meshseal.render.opengl import OpenGLRenderer

FIXTURES = Path(__file__).resolve().parents[1] / "tests" / "fixtures"
MESHES = ["bunny.glb", "suzanne.glb", "teapot/teapot.obj", "sh3d_crate/crate.obj", "sh3d_deckChair/deckChair.obj",
          "multi_material.glb"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None)
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    watermarker = meshseal.load(args.model)
    renderer = OpenGLRenderer()
    generator = torch.Generator().manual_seed(args.seed)
    accuracies = []
    with tempfile.TemporaryDirectory() as folder:
        for name in MESHES:
            original = meshseal.load_mesh(FIXTURES / name)
            bits = "".join(str(int(b)) for b in torch.randint(0, 2, (watermarker.n_bits,), generator=generator))
            marked = normalize(to_z_up(watermarker.embed(original, bits)))
            cameras, lights = sample_seed_cameras(args.views, generator), sample_seed_lights(args.views, generator)
            rgba = renderer.render(marked, cameras, lights, args.size, args.size, background=(0.8, 0.8, 0.8))
            prepared = watermarker.original(original) if watermarker.informed else None
            for view in range(args.views):
                path = Path(folder) / f"{Path(name).stem}_{view}.png"
                Image.fromarray((rgba[view, ..., :3].numpy() * 255 + 0.5).astype(np.uint8)).save(path)
                result = (watermarker.detect(path, prepared, register=True) if prepared is not None
                          else watermarker.detect(path))
                accuracy = sum(a == b for a, b in zip(result.bits, bits)) / len(bits)
                accuracies.append(accuracy)
                iou = "" if result.registration_iou is None else f" registration IoU {result.registration_iou:.3f}"
                print(f"{name} view {view}: bit_acc {accuracy:.4f}{iou}", flush=True)
    print(f"mean bit_acc {sum(accuracies) / len(accuracies):.4f} over {len(accuracies)} OpenGL pictures")


if __name__ == "__main__":
    main()
