"""Where registration's start comes from: the picture's object mask against the pixels the object
really covers at least half, and what registering on each gives.

For the given test meshes (marked and rendered as experiments/registration_conditions.py renders
"plain": one seeded view, a plain background, 8-bit, no metadata) it prints the IoU with the true
half-covered pixels (the render's alpha >= 0.5) of `object_mask` untrimmed (every pixel off the
background, as before `framing.half_covered`) and trimmed (as shipped), the pose error (px at 256^2)
of `register` on each of the three masks, and the texture misfit (`register.texture_misfit`, bands
PICK_SIGMAS) of the untrimmed mask's camera against the true camera's.

    python experiments/registration_masks.py --data data --meshes 36 43 46 70 71 77 81
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

import meshseal
from meshseal import payload
from meshseal.data.dataset import MeshDataset, collate
from meshseal.framing import object_mask
from meshseal.pipeline import batch_mark_grid, batch_texels_used, random_backgrounds, sample_views
from meshseal.register import PICK_SIGMAS, pose_error, register, texture_misfit
from meshseal.render import MeshBatch, MeshRenderer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--meshes", type=int, nargs="+", required=True, help="test-split indices")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    model = meshseal.load().model
    dataset = MeshDataset(args.data, "test")
    iou = lambda a, b: float((a & b).sum() / max((a | b).sum(), 1))  # noqa: E731
    print("| mesh | mask IoU untrimmed | trimmed | pose, untrimmed mask | trimmed | true half-covered | "
          "texture misfit, untrimmed camera | true camera |")
    print("|---|---|---|---|---|---|---|---|")
    for index in args.meshes:
        batch = collate([dataset[index]], "cpu")
        positions, normals, uvs, faces, texture = (batch[k] for k in ("positions", "normals", "uvs", "faces", "texture"))
        original = MeshBatch.from_tensors(positions, normals, uvs, faces, texture)
        generator = torch.Generator().manual_seed(args.seed * 100003 + index)  # registration_conditions' draws
        message = payload.encode(int(torch.randint(0, 2 ** 31, (1,), generator=generator)), None, model.n_bits)[None]
        with torch.no_grad():
            marked = model.mark_texture(texture, message, 1.0, payload.key_seed(None), batch_mark_grid(model, batch),
                                        batch_texels_used(batch))
            cameras, lights = sample_views(1, "seed", generator)
            out = MeshRenderer()(MeshBatch.from_tensors(positions, normals, uvs, faces, marked), cameras, lights,
                                 256, 256, torch.zeros(1, 3))
            alpha = out.rgba[0, ..., 3]
            background = random_backgrounds(1, generator)[0]
            picture = (out.image[0] + (1 - alpha[None]) * background[:, None, None]).clamp(0, 1)
        pixels = (picture.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8).astype(np.float32) / 255
        picture = torch.from_numpy(pixels).permute(2, 0, 1)
        truth = alpha.numpy() >= 0.5
        untrimmed, found_background = object_mask(pixels, trim=False)
        trimmed, _ = object_mask(pixels)
        found = {}
        with torch.enable_grad():
            for name, mask in (("untrimmed", untrimmed), ("trimmed", trimmed), ("truth", truth)):
                found[name] = register(original, picture, torch.from_numpy(mask), torch.from_numpy(found_background)).camera
        pose = {name: pose_error(original, cameras, camera, 256, 256) for name, camera in found.items()}
        misfit = [texture_misfit(original, camera, picture[None], torch.from_numpy(untrimmed).float()[None], PICK_SIGMAS)
                  for camera in (found["untrimmed"], cameras)]
        print(f"| {index} | {iou(untrimmed, truth):.3f} | {iou(trimmed, truth):.3f} | {pose['untrimmed']:.2f} | "
              f"{pose['trimmed']:.2f} | {pose['truth']:.2f} | {misfit[0]:.3f} | {misfit[1]:.3f} |", flush=True)


if __name__ == "__main__":
    main()
