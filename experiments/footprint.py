"""The matched filter's footprint (`pipeline.picture_footprint`): pictures whose pixels average the
surface over their area, read with and without a prediction and template sampled the same way.

Our renderer samples the texture at each pixel's centre; Blender, game engines (antialiasing, pixel
filters, mipmaps), resizing and blur average it over the pixel's footprint, which blurs away the mark's
finest cells and leaves the host texture's detail in a point-sampled prediction's residual. For test
meshes START .. START+N-1, the shipped mark (a random message, public key, strength 1), one seeded view
of the paper's range, plain random background, 8-bit values, camera known: the picture as ours
renders it (point), the 1024^2 render averaged over 4 x 4 sub-pixels (area), the same after a 0.5 px
Gaussian (area + blur, about a Blackman-Harris pixel filter of 1.5 px) and the 1024^2 render averaged
to 128^2 (a half-size picture). Prints a markdown table: bit accuracy, the detection rate at the FPR
1e-6 threshold, how often each footprint was chosen, and the standard deviation of z under five wrong
keys (the null: should stay 1).

    python experiments/footprint.py --data data [--start 0] [--meshes 100]
"""

from __future__ import annotations

import argparse
from collections import Counter

import numpy as np
import torch
import torch.nn.functional as F

import meshseal
from meshseal import payload
from meshseal.data.dataset import MeshDataset, collate
from meshseal.imaging import gaussian_blur
from meshseal.models.spread import soft_bits
from meshseal.reading.footprint import picture_footprint
from meshseal.training.views import random_backgrounds
from meshseal.render.views import sample_views
from meshseal.reading.relight import relit_residual
from meshseal.methods.spread import spread_evidence
from meshseal.render import MeshBatch, MeshRenderer


def pictures(model, dataset: MeshDataset, index: int):
    """Test mesh `index` marked with a seeded message: the original, the true camera, the message and
    its four pictures (name -> (1, 3, S, S), 8-bit values)."""
    generator = torch.Generator().manual_seed(1000 + index)
    batch = collate([dataset[index]], "cpu")
    positions, normals, uvs, faces, texture = (batch[k] for k in ("positions", "normals", "uvs", "faces", "texture"))
    message = torch.randint(0, 2, (1, model.n_bits), generator=generator).float()
    marked = model.texture_encoder(texture, message, 1.0, payload.key_seed(None))
    cameras, lights = sample_views(1, "seed", generator)
    background = random_backgrounds(1, generator)
    mesh = MeshBatch.from_tensors(positions, normals, uvs, faces, marked)
    fine = MeshRenderer()(mesh, cameras, lights, 1024, 1024, background).image.clamp(0, 1)
    seen = {"point": MeshRenderer()(mesh, cameras, lights, 256, 256, background).image.clamp(0, 1),
            "area": F.avg_pool2d(fine, 4), "area + 0.5 px blur": F.avg_pool2d(gaussian_blur(fine, 2.0), 4),
            "half size (128^2)": F.avg_pool2d(fine, 8)}
    original = MeshBatch.from_tensors(positions, normals, uvs, faces, texture)
    return original, cameras, message[0], {name: torch.round(p * 255) / 255 for name, p in seen.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--meshes", type=int, default=100)
    args = parser.parse_args()
    model = meshseal.load().model
    dataset = MeshDataset(args.data, "test")
    public = payload.key_seed(None)
    rows, chosen, null = {}, {}, {}
    for index in range(args.start, min(len(dataset), args.start + args.meshes)):
        with torch.no_grad():
            original, cameras, message, seen = pictures(model, dataset, index)
            for name, picture in seen.items():
                size = picture.shape[-1]
                found = picture_footprint(original, relit_residual(original, picture, cameras), cameras, size, size)
                sigma = float(found.sigma[0])
                chosen.setdefault(name, Counter())["point" if np.isnan(sigma) else f"area + {sigma:g} px"] += 1
                for footprint in (False, True):
                    evidence = spread_evidence(model, original, picture, cameras, footprint=footprint)
                    z = soft_bits(model.texture_encoder, evidence, public)[0].double()
                    rows.setdefault((name, footprint), []).append(
                        (float(((z > 0).double() == message).double().mean()), payload.detected(payload.detection_pvalue(z))))
                    null.setdefault(footprint, []).extend(soft_bits(model.texture_encoder, evidence, 7919 + k)[0] for k in range(5))
        print(f"mesh {index} done", flush=True)
    print("\n| picture | bit acc. / detected, centre samples | bit acc. / detected, footprint | footprints chosen |")
    print("|---|---|---|---|")
    for name in chosen:
        cells = [f"{np.mean([r[0] for r in rows[name, f]]):.4f} / {np.mean([r[1] for r in rows[name, f]]):.2f}"
                 for f in (False, True)]
        print(f"| {name} | " + " | ".join(cells) + " | " + ", ".join(f"{k} {v}" for k, v in chosen[name].most_common()) + " |")
    for footprint in (False, True):
        values = torch.cat(null[footprint])
        print(f"null z std under wrong keys, footprint {footprint}: {float(values[values != 0].std()):.3f}")


if __name__ == "__main__":
    main()
