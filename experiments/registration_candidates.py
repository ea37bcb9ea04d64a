"""Where registration fails on the test split: the search (no candidate near the true view) or the
refinement (a good candidate refined to the wrong pose).

For test meshes START .. START+N-1: mark the texture with the shipped model, render one seeded 256^2
view (8-bit values, plain random background), register it as `meshseal detect` does, and print one
JSON line per picture: the final pose error in pixels and silhouette IoU, the angle between the true
view direction and the found one, the angles of the 8 refined candidates after the silhouette stage
(best-scored first), and the seconds taken.

    python experiments/registration_candidates.py --data data [--start 0] [--meshes 30]
"""

from __future__ import annotations

import argparse
import json
import time

import torch
import torch.nn.functional as F

import meshseal
from meshseal import payload
from meshseal import register as registration
from meshseal.data.dataset import MeshDataset, collate
from meshseal.framing import object_mask
from meshseal.pipeline import random_backgrounds, sample_views
from meshseal.render import MeshBatch, MeshRenderer


def _degrees(cameras, truth) -> torch.Tensor:
    """Angles (B,) between the view directions of `cameras` and of the one camera `truth`."""
    views = F.normalize(cameras.eye - cameras.at, dim=-1)
    true_view = F.normalize(truth.eye - truth.at, dim=-1)
    return torch.rad2deg(torch.acos((views @ true_view.T).clamp(-1, 1)))[:, 0]


def seeded_picture(model, dataset: MeshDataset, index: int):
    """Test mesh `index` marked by `model`, seen from one seeded 256^2 view (8-bit values, plain random
    background): the original mesh, the true camera, the picture (1, 3, 256, 256), and the object
    mask (H, W) and background colour found from it as `meshseal detect` finds them."""
    generator = torch.Generator().manual_seed(1000 + index)
    batch = collate([dataset[index]], "cpu")
    positions, normals, uvs, faces, texture = (batch[k] for k in ("positions", "normals", "uvs", "faces", "texture"))
    message = torch.randint(0, 2, (1, model.n_bits), generator=generator).float()
    with torch.no_grad():
        marked = model.mark_texture(texture, message, 1.0, payload.key_seed(None))
        cameras, lights = sample_views(1, "seed", generator)
        picture = MeshRenderer()(MeshBatch.from_tensors(positions, normals, uvs, faces, marked), cameras, lights,
                                 256, 256, random_backgrounds(1, generator)).image.clamp(0, 1)
        picture = torch.round(picture * 255) / 255
    mask, background = object_mask(picture[0].permute(1, 2, 0).numpy())
    return MeshBatch.from_tensors(positions, normals, uvs, faces, texture), cameras, picture, mask, background


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--meshes", type=int, default=30)
    args = parser.parse_args()
    model = meshseal.load().model
    dataset = MeshDataset(args.data, "test")
    refined = {}
    refine = registration._refine_silhouettes

    def keep_candidates(mesh, cameras, level, sigma, *rest, **options):
        out = refine(mesh, cameras, level, sigma, *rest, **options)
        if sigma == registration.COARSE_SILHOUETTE_SIGMAS[-1]:  # the candidates' silhouette stage, done
            refined["candidates"] = out
        return out

    registration._refine_silhouettes = keep_candidates
    for index in range(args.start, min(len(dataset), args.start + args.meshes)):
        original, cameras, picture, mask, background = seeded_picture(model, dataset, index)
        started = time.perf_counter()
        found = registration.register(original, picture[0], torch.from_numpy(mask),
                                      torch.tensor(background, dtype=torch.float32))
        seconds = time.perf_counter() - started
        candidates = _degrees(refined.pop("candidates", found.camera), cameras)
        print(json.dumps({"mesh": index, "id": dataset.rows[index]["id"],
                          "pose_error_px": round(registration.pose_error(original, cameras, found.camera, 256, 256), 3),
                          "iou": round(found.iou, 3),
                          "view_error_deg": round(float(_degrees(found.camera, cameras)[0]), 1),
                          "candidates_deg": [round(float(a), 1) for a in candidates],
                          "seconds": round(seconds, 1)}), flush=True)


if __name__ == "__main__":
    main()
