"""The matched filter's whitening (`models.spread.whiten`): what the high-pass and the inverse-variance
weighting each buy, with the camera known and a fraction of a pixel off.

For test meshes START .. START+N-1: the pictures of `registration_candidates.py` (the shipped mark,
one seeded 256^2 view, 8-bit values, plain random background), read with the true camera and with one
moved by about 0.25, 0.5 and 1 px (`pipeline.jitter_cameras`, seeded), under each whitening: none, the
high-pass alone, the weighting alone, both (what `meshseal detect` runs). Prints a markdown table: bit
accuracy, the detection rate at the FPR 1e-6 threshold, and the standard deviation of z under five
wrong keys (the null: should stay 1).

    python experiments/whitening.py --data data [--start 0] [--meshes 100]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from registration_candidates import seeded_picture

import meshseal
from meshseal import payload
from meshseal.data.dataset import MeshDataset
from meshseal.models.spread import soft_bits
from meshseal.pipeline import jitter_cameras, spread_evidence

WHITENINGS = {"none": {"highpass": None, "window": None}, "high-pass": {"window": None},
              "weighting": {"highpass": None}, "both (shipped)": {}}
JITTERS = (0.0, 0.25, 0.5, 1.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--meshes", type=int, default=100)
    args = parser.parse_args()
    model = meshseal.load().model
    dataset = MeshDataset(args.data, "test")
    public = payload.key_seed(None)
    rows = {(name, jitter): [] for name in WHITENINGS for jitter in JITTERS}
    null = {name: [] for name in WHITENINGS}
    for index in range(args.start, min(len(dataset), args.start + args.meshes)):
        original, cameras, picture, _, _ = seeded_picture(model, dataset, index)
        message = torch.randint(0, 2, (1, model.n_bits), generator=torch.Generator().manual_seed(1000 + index))[0]
        for jitter in JITTERS:
            camera = jitter_cameras(cameras, jitter, 256, torch.Generator().manual_seed(index))
            for name, options in WHITENINGS.items():
                with torch.no_grad():
                    evidence = spread_evidence(model, original, picture, camera, options)
                z = soft_bits(model.texture_encoder, evidence, public)[0].double()
                rows[name, jitter].append((float(((z > 0).long() == message).double().mean()),
                                           payload.detected(payload.detection_pvalue(z))))
                if jitter == 0.0:
                    null[name] += [soft_bits(model.texture_encoder, evidence, 7919 + k)[0] for k in range(5)]
        print(f"mesh {index} done", flush=True)
    print("\n| whitening | " + " | ".join(f"{j:g} px: bit acc / detected" for j in JITTERS) + " | null z std |")
    print("|---" * (len(JITTERS) + 2) + "|")
    for name in WHITENINGS:
        cells = [f"{np.mean([r[0] for r in rows[name, j]]):.4f} / {np.mean([r[1] for r in rows[name, j]]):.2f}"
                 for j in JITTERS]
        values = torch.cat(null[name])
        print(f"| {name} | " + " | ".join(cells) + f" | {float(values[values != 0].std()):.3f} |")


if __name__ == "__main__":
    main()
