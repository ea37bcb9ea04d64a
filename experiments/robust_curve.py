"""Detection against visibility for each lossy format: the `robust` mark (configs/robust.yaml) at several
texture PSNRs, and the default's blue-yellow mark beside it, read the same way.

Each mark is built from configs/robust.yaml with `mark_colour` and `texture_psnr` changed (nothing is
learned), then `meshseal eval --attacks` runs in-process: the first N test meshes, one seeded 256^2 view
each (`--views`), marked at full strength (no FLIP budget, so that the strength is the one named), saved as 8-bit
PNG, attacked, read with the camera known. One Markdown table row per mark: object FLIP and PSNR, then
detected / exact message per attack at FPR 1e-6.

    python experiments/robust_curve.py --data data --meshes 30 [--psnr 40 37 34 31] [--colours grey blue-yellow]
        [--set chips=64 --set coarse_chips=32 ...]   (any model setting of configs/robust.yaml overridden)
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
import yaml

from meshseal.data.dataset import MeshDataset
from meshseal.evaluation.attacks import parse
from meshseal.evaluation.evaluate import evaluate_registered
from meshseal.models import ModelConfig, WatermarkModel

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--meshes", type=int, default=30)
    parser.add_argument("--start", type=int, default=0, help="the first test mesh (default 0)")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--views", type=int, default=1, help="seeded views of each mesh (default 1)")
    parser.add_argument("--psnr", type=float, nargs="+", default=[40.0, 37.0, 34.0, 31.0])
    parser.add_argument("--colours", nargs="+", default=["grey", "blue-yellow"])
    parser.add_argument("--attacks", default="none,jpeg90,jpeg75,jpeg50,webp80")
    parser.add_argument("--kind", choices=("magnified", "minified"), default=None,
                        help="only the test meshes of this kind under configs/default.yaml's grids (of the first "
                             "--scan): magnified textures (cells over fine_above px), minified (under coarse_below, "
                             "with coarse_chips 32)")
    parser.add_argument("--scan", type=int, default=284, help="test meshes to look through for --kind")
    parser.add_argument("--dequantize", type=float, default=None,
                        help="the reading's JPEG dequantisation prior (reading.compression.DEQUANTIZE_SIGMA; 0: off)")
    parser.add_argument("--config", type=Path, default=ROOT / "configs" / "robust.yaml",
                        help="the model config the marks start from (default configs/robust.yaml)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a model setting (YAML value), repeatable")
    args = parser.parse_args()
    if args.dequantize is not None:
        from meshseal.reading import compression

        compression.DEQUANTIZE_SIGMA = args.dequantize
        print(f"<!-- JPEG dequantisation prior sigma {args.dequantize:g} -->")
    base = yaml.safe_load(args.config.read_text())["model"]
    for item in args.set:
        key, value = item.split("=", 1)
        base[key] = yaml.safe_load(value)
    if args.set:
        print(f"<!-- settings: {' '.join(args.set)} -->")
    attacks = parse(args.attacks)
    dataset = MeshDataset(args.data, "test", seed=0)
    if args.start:
        dataset = _Subset(dataset, list(range(args.start, len(dataset))))
    if args.kind:
        dataset = _of_kind(dataset, args.kind, args.scan)
        print(f"<!-- {len(dataset)} {args.kind} meshes of the first {args.scan} -->")
    print("| mark | texture PSNR (dB) | object FLIP mean / p95 | object PSNR (dB) | "
          + " | ".join(f"{a}: detected / exact" for a in attacks) + " |")
    print("|---|---|---|---|" + "---|" * len(attacks))
    for colour in args.colours:
        for psnr in args.psnr:
            started = time.time()
            torch.manual_seed(0)
            model = WatermarkModel(ModelConfig.from_dict(base | {"mark_colour": colour, "texture_psnr": psnr}))
            m = evaluate_registered(model, dataset, args.meshes, 0, args.size, "seed", None, views=args.views, register=False,
                                    max_flip=None, attacks=attacks)
            cells = " | ".join(f"{m['attacks'][a]['detected']:.2f} / {m['attacks'][a]['exact']:.2f}" for a in attacks)
            print(f"| {colour} | {psnr:g} | {m['flip_object']:.4f} / {m['flip_object_p95']:.4f} | {m['psnr_object']:.2f} | "
                  f"{cells} |", flush=True)
            named = " ".join(f"{a} {m['attacks'][a]['named']:.2f}/{m['attacks'][a]['bit_acc']:.3f}" for a in attacks)
            print(f"<!-- {colour} {psnr:g}: {m['n_meshes']} meshes, {time.time() - started:.0f} s; named / bit accuracy: "
                  f"{named} -->", flush=True)
            for kind, entry in m.get("by_kind", {}).items():  # detected by kind of picture, so no class hides in the mean
                row = " ".join(f"{a} {entry[a]:.2f}" for a in attacks if entry.get(a) is not None)
                print(f"<!-- {colour} {psnr:g} {kind} ({entry['pictures']} pictures): detected {row} -->", flush=True)


class _Subset:
    """Some items of a dataset, as `evaluate_registered` takes one."""

    def __init__(self, dataset, indices):
        self.dataset, self.indices = dataset, indices

    def __len__(self):
        return len(self.indices)

    def __getitem__(self, index):
        return self.dataset[self.indices[index]]


def _of_kind(dataset, kind: str, scan: int) -> _Subset:
    """The test meshes whose texture the default's grids call magnified (cells of its 64^2 grid over
    `fine_above` px in a standard view) or minified (under `coarse_below` px)."""
    from meshseal.data.dataset import collate
    from meshseal.methods.batches import unpadded
    from meshseal.models.spread import cell_pixels

    config = yaml.safe_load((ROOT / "configs" / "default.yaml").read_text())["model"]
    chosen = []
    for index in range(min(scan, len(dataset))):
        positions, _, uvs, faces = unpadded(collate([dataset[index]], "cpu"), 0)
        width = cell_pixels(positions, faces, uvs, config["chips"])
        if (kind == "magnified" and width > config["fine_above"]) or (kind == "minified" and width < 0.6):
            chosen.append(index)
    return _Subset(dataset, chosen)


if __name__ == "__main__":
    main()
