"""What a learned blind decoder reads from baked views against real renders of the same views.

    python experiments/gbuffer_gap.py --model runs/blind8_gb_coords_more/model.safetensors --data data

For the seed protocol's test meshes (spherical UVs, noise or real textures), each marked as `meshseal
embed` marks it with a random message, one seed camera and light each, prints the bit accuracy of:
`baked` (the G-buffer view the trainer composites, 128^2 framed), `baked_x2` (baked at twice the size,
box-filtered: `gbuffer_supersample: 2`), `render` (the differentiable renderer's 600 x 400 picture, its
splatted edges, framed as `meshseal detect` frames it) and `render_hard` (the same with hard edges).
"""

from __future__ import annotations

import argparse

import torch
import torch.nn.functional as F

from meshseal.data.dataset import MeshDataset, collate
from meshseal.methods import method_for
from meshseal.models.io import load_model
from meshseal.reading.framing import frame
from meshseal.render import MeshBatch, MeshRenderer
from meshseal.render.views import sample_views
from meshseal.training.gbuffer import bake_views, composite
from meshseal.training.losses import bit_accuracy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--data", default="data")
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()
    model = load_model(args.model).eval()
    method = method_for(model)
    size = model.config.frame_size
    dataset = MeshDataset(args.data, "test", seed=0, texture_kinds=["noise", "real"])
    generator = torch.Generator().manual_seed(args.seed)
    reads: dict[str, list] = {}
    with torch.no_grad():
        for start in range(0, len(dataset), 16):
            batch = collate([dataset[i] for i in range(start, min(len(dataset), start + 16))])
            n = batch["positions"].shape[0]
            message = torch.randint(0, 2, (n, model.n_bits), generator=generator).float()
            marked = method.mark_batch(batch, message, None)[2]
            cameras, lights = sample_views(n, "seed", generator)
            background = torch.zeros(n, 3)
            pictures = {"baked": composite(marked, bake_views(batch, cameras, lights, size), background),
                        "baked_x2": F.avg_pool2d(composite(marked, bake_views(batch, cameras, lights, 2 * size),
                                                           background), 2)}
            for name, blend in (("render", "splat"), ("render_hard", "hard")):
                mesh = MeshBatch.from_tensors(batch["positions"], batch["normals"], batch["uvs"], batch["faces"], marked)
                out = MeshRenderer(blend=blend)(mesh, cameras, lights, 400, 600, background)
                pictures[name] = frame(out.image, out.rgba[..., 3], size, background)
            for name, picture in pictures.items():
                reads.setdefault(name, []).append(bit_accuracy(model.decode(picture), message))
    print(f"{len(dataset)} test meshes, one seed view each")
    for name, values in reads.items():
        print(f"{name}: bit accuracy {float(torch.cat(values).mean()):.4f}")


if __name__ == "__main__":
    main()
