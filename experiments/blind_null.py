"""Are the blind model's `--expect` p-values honest? Unmarked pictures in the seed paper's protocol (the
test items with spherical UVs and a noise or real texture, one seed-range camera and light each, 600 x
400), each tested against random expected asset IDs as `meshseal detect --model blind --expect-id N`
tests them (the binomial p-value of the hard bits that agree with the encoded ID): the share of
p-values at or below each level should not exceed the level.

python experiments/blind_null.py --data data [--ids 200] [--model blind]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

import meshseal
from meshseal import payload
from meshseal.data.dataset import MeshDataset
from meshseal.evaluation.metrics import visibility
from meshseal.reading.framing import object_mask
from meshseal.models.surface import VIEW_SIZE, read_picture
from meshseal.render import MeshBatch, MeshRenderer, sample_seed_cameras, sample_seed_lights


def render_pair(item: dict, texture: torch.Tensor, marked: torch.Tensor, generator: torch.Generator,
                height: int, width: int):
    """The original and the marked `item` rendered from one seed-range camera and light drawn from
    `generator`, as 8-bit pictures (H, W, 3), and the mark's visibility over the object's pixels."""
    cameras, lights = sample_seed_cameras(1, generator), sample_seed_lights(1, generator)
    renderer, pictures = MeshRenderer(), []
    for tex in (texture, marked):
        batch = MeshBatch.from_tensors(item["positions"][None], item["normals"][None], item["uvs"][None],
                                       item["faces"], tex)
        with torch.no_grad():
            pictures.append(renderer(batch, cameras, lights, height, width).rgba[0])
    original, picture = (torch.round(p[..., :3].clamp(0, 1) * 255) / 255 for p in pictures)
    coverage = pictures[0][..., 3] > 0.5
    return original, picture, visibility(original.permute(2, 0, 1)[None], picture.permute(2, 0, 1)[None],
                                          coverage[None])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="data")
    parser.add_argument("--model", default="blind")
    parser.add_argument("--ids", type=int, default=200, help="random expected IDs per picture")
    parser.add_argument("--seed", type=int, default=5)
    args = parser.parse_args()

    watermarker = meshseal.load(args.model)
    dataset = MeshDataset(args.data, "test", seed=0, texture_kinds=("noise", "real"))
    generator, rng = torch.Generator().manual_seed(args.seed), np.random.default_rng(args.seed)
    top = 2 ** payload.payload_bits(watermarker.n_bits)
    pvalues = []
    for index in range(len(dataset)):
        item = dataset[index]
        texture = item["texture"][None]
        original, _, _ = render_pair(item, texture, texture, generator, *VIEW_SIZE)
        image = original.numpy().astype(np.float64)
        bits = (read_picture(watermarker.model.texture_encoder, image, object_mask(image)[0]) > 0).int().numpy()
        for identity in rng.integers(0, top, args.ids):
            expected = payload.encode(int(identity), None, watermarker.n_bits).numpy().astype(int)
            pvalues.append(payload.binomial_pvalue(int((bits == expected).sum()), watermarker.n_bits))
    pvalues = np.array(pvalues)
    print(f"{len(dataset)} unmarked pictures x {args.ids} expected IDs = {len(pvalues)} tests")
    for level in (0.1, 0.01, 1e-3, 1e-4):
        print(f"share of p-values <= {level:g}: {np.mean(pvalues <= level):.5f}")


if __name__ == "__main__":
    main()
