"""The matched filter's template for a resized picture (`reading.footprint.RESAMPLED_ADJOINT`, `RESAMPLED_TEMPLATE_SIGMA`): the
test meshes [start, start + meshes) of a built dataset, one seeded 256^2 view each, marked by the shipped
default at strength 1 with a random ID (as experiments/soft_decoding.py marks them), resized by each
attack and read with the camera known under each template sigma. Per attack and sigma: the pictures
detected at FPR 1e-6; per attack, against the first sigma given, how many read a lower p-value and the
median log10 ratio of the p-values (the evidence's strength, below the detection threshold too).

    python experiments/resized_template.py --data data --start 0 --meshes 160 \
        [--attacks resize0.5,resize0.75,resize1.5] [--sigmas 0.25,adjoint]  (any of 0.5, 0.25, 0.15, adjoint)

The sigma `adjoint` reads with the resize's own adjoint (`footprint.RESAMPLED_ADJOINT`, shipped: the
residual carried back through the bicubic resize onto the source render's pixels); a number reads with
the pixel's area blurred by that many pixels instead.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--meshes", type=int, default=160)
    parser.add_argument("--attacks", default="resize0.5,resize0.75,resize1.5")
    parser.add_argument("--sigmas", default="0.25,adjoint")
    args = parser.parse_args()
    from meshseal.threads import configure

    configure()
    import numpy as np
    import torch

    import meshseal
    import meshseal.reading.footprint as footprint
    from meshseal.data.dataset import MeshDataset
    from meshseal.evaluation.attacks import apply as attack_picture
    from soft_decoding import marked_picture  # the same pictures as that experiment's

    watermarker = meshseal.load()
    encoder = watermarker.model
    dataset = MeshDataset(args.data, "test", seed=0)
    generator = torch.Generator().manual_seed(2_000_003)
    attacks, sigmas = args.attacks.split(","), args.sigmas.split(",")
    shipped = footprint.RESAMPLED_TEMPLATE_SIGMA, footprint.RESAMPLED_ADJOINT
    rows = []
    for index in range(args.start, min(args.start + args.meshes, len(dataset))):
        picture, original, cameras, _ = marked_picture(encoder, dataset[index], generator)
        row = {"mesh": index}
        for number, attack in enumerate(attacks):
            hit = attack_picture(attack, picture, np.random.default_rng([0, index, 0, number]))
            for sigma in sigmas:
                if sigma == "adjoint":  # the resize's own adjoint (`footprint.RESAMPLED_ADJOINT`)
                    footprint.RESAMPLED_ADJOINT = True
                else:
                    footprint.RESAMPLED_TEMPLATE_SIGMA, footprint.RESAMPLED_ADJOINT = float(sigma), False
                try:
                    found = watermarker.decide([watermarker.read(hit.astype(np.float32) / 255.0, original, camera=cameras)])
                    row[f"{attack}@{sigma}"] = (bool(found.detected), float(found.p_value))
                except meshseal.MeshsealError:
                    row[f"{attack}@{sigma}"] = (False, 1.0)
                finally:
                    footprint.RESAMPLED_TEMPLATE_SIGMA, footprint.RESAMPLED_ADJOINT = shipped
        rows.append(row)
        print(json.dumps(row), flush=True)
    print(f"\nfirst {len(rows)} test meshes from {args.start}, one view each, camera known, FPR 1e-6\n")
    print("| attack | " + " | ".join(f"template {s}: detected" for s in sigmas) + " | "
          + " | ".join(f"template {s} against {sigmas[0]}: lower p / median log10 ratio" for s in sigmas[1:]) + " |")
    print("|---|" + "---|" * (2 * len(sigmas) - 1))
    for attack in attacks:
        cells = [str(sum(r[f"{attack}@{s}"][0] for r in rows)) for s in sigmas]
        for sigma in sigmas[1:]:
            pairs = [(r[f"{attack}@{sigma}"][1], r[f"{attack}@{sigmas[0]}"][1]) for r in rows]
            ratios = [math.log10(a) - math.log10(b) for a, b in pairs if a > 0 and b > 0]
            cells.append(f"{sum(a < b * 0.999 for a, b in pairs)} / {statistics.median(ratios):.2f}" if ratios else "-")
        print(f"| {attack} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
