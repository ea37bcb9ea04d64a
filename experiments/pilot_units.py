"""The pilot's units (the cell or block sums its signs cover) picture by picture, and what a transform of
them applied before the pilot's test would detect. Any function of the units alone keeps the test's
exact null (the key's signs are fair coins independent of the picture), so a transform that tames
heavy-tailed host error (clipped at a robust scale, a power, the signs alone) is a free choice; this
measures whether one reads more. The first N test meshes, one seeded 256^2 view each, marked by the
default at full strength and read with the camera known (as `experiments/picture_log.py` reads them),
as PNG and after each attack; detection from the pilot alone (its p-value on the normal approximation,
times the grids, over the pilot's 0.9 share of 1e-6).

    python experiments/pilot_units.py --data data --meshes 100 --attacks jpeg90,jpeg75,jpeg50,webp80 --out UNITS.npz
    python experiments/pilot_units.py --analyse UNITS.npz
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def record(args) -> None:
    import torch
    import yaml

    from meshseal.data.dataset import MeshDataset
    from meshseal.evaluation import evaluate as ev
    from meshseal.evaluation.attacks import parse
    from meshseal.models import ModelConfig, WatermarkModel
    from meshseal.models.spread import split_grids
    from picture_log import hook_readings

    config = yaml.safe_load(args.config.read_text())["model"]
    model = WatermarkModel(ModelConfig.from_dict(config))
    dataset = MeshDataset(args.data, "test", seed=0)
    order = ["png"] + list(parse(args.attacks))
    units, meta = [], []

    def handle(state, watermarker, reading, attack):
        if reading is None:
            return
        method = watermarker.method
        encoder = method.encoder
        evidence = reading.evidence if reading.evidence.dim() == 2 else reading.evidence[None]
        for grid, sums in enumerate(split_grids(encoder, evidence)):
            sums = sums[0].double()
            chips = math.isqrt(sums.shape[-1])
            assign, sign = encoder.pattern(method.key_seed(None), chips)
            pilot = assign == encoder.n_bits
            cells, sign = sums * pilot, sign.to(sums)
            wide = encoder.pilot_width(chips)
            if wide > 1:  # as `models.spread.pilot_z`: a block's cells summed, one sign a block
                side = chips // wide
                cells = cells.reshape(side, wide, side, wide).sum((1, 3)).reshape(-1)
                sign = sign.reshape(side, wide, side, wide)[:, 0, :, 0].reshape(-1)
                pilot = torch.ones_like(cells, dtype=torch.bool)
            seen = pilot & (cells != 0)
            units.append(np.stack([cells[seen].numpy(), sign[seen].numpy()]))
            meta.append({"mesh": state["mesh"], "attack": attack, "grid": grid, "kinds": state["kinds"][0]})

    hook_readings(order, handle)
    torch.manual_seed(0)
    ev.evaluate_registered(model, dataset, args.meshes, 0, 256, "seed", None, views=1, register=False,
                           max_flip=None, attacks=parse(args.attacks))
    np.savez_compressed(args.out, meta=json.dumps(meta), **{f"u{i}": u for i, u in enumerate(units)})
    print(f"{len(units)} grids read -> {args.out}")


def _mad_clip(c: float):
    def transform(u: np.ndarray) -> np.ndarray:
        scale = 1.4826 * np.median(np.abs(u)) + 1e-30
        return np.clip(u, -c * scale, c * scale)
    return transform


def _rms_clip(c: float):
    def transform(u: np.ndarray) -> np.ndarray:
        scale = np.sqrt(np.mean(u * u)) + 1e-30
        return np.clip(u, -c * scale, c * scale)
    return transform


TRANSFORMS = {
    "none (the default)": lambda u: u,
    "clipped at 4 MAD": _mad_clip(4.0), "clipped at 2 MAD": _mad_clip(2.0), "clipped at 1 MAD": _mad_clip(1.0),
    "clipped at 3 RMS": _rms_clip(3.0), "clipped at 2 RMS": _rms_clip(2.0), "clipped at 1.5 RMS": _rms_clip(1.5),
    "|u|^0.75": lambda u: np.sign(u) * np.abs(u) ** 0.75, "|u|^0.5": lambda u: np.sign(u) * np.abs(u) ** 0.5,
    "signs alone": np.sign,
}


def analyse(path: Path) -> None:
    from scipy.stats import kurtosis, norm

    data = np.load(path)
    meta = json.loads(str(data["meta"]))
    pictures: dict = {}
    for index, entry in enumerate(meta):
        pictures.setdefault((entry["mesh"], entry["attack"]), []).append(data[f"u{index}"])
    attacks = list(dict.fromkeys(entry["attack"] for entry in meta))
    print("Excess kurtosis of the units, median over pictures: " + ", ".join(
        f"{attack} {np.median([kurtosis(u[0]) for key, grids in pictures.items() if key[1] == attack for u in grids if u.shape[1] > 20]):.1f}"
        for attack in attacks) + "\n")
    print("| transform | " + " | ".join(attacks) + " |\n|---|" + "---|" * len(attacks))
    for name, transform in TRANSFORMS.items():
        cells = []
        for attack in attacks:
            detected, zs = [], []
            for key, grids in pictures.items():
                if key[1] != attack:
                    continue
                z = [float((transform(u[0]) * u[1]).sum() / np.sqrt((transform(u[0]) ** 2).sum() + 1e-30))
                     for u in grids if u.shape[1]]
                zs.append(max(z) if z else 0.0)
                p = min(1.0, len(z) * min(norm.sf(v) for v in z)) if z else 1.0
                detected.append(p / 0.9 <= 1e-6)
            cells.append(f"{np.mean(detected):.2f} (z {np.median(zs):.2f})")
        print(f"| {name} | " + " | ".join(cells) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT / "data")
    parser.add_argument("--meshes", type=int, default=100)
    parser.add_argument("--attacks", default="jpeg90,jpeg75,jpeg50,webp80")
    parser.add_argument("--config", type=Path, default=ROOT / "configs" / "default.yaml")
    parser.add_argument("--out", type=Path, default=Path("pilot_units.npz"))
    parser.add_argument("--analyse", type=Path, default=None, help="a file this script wrote: the table")
    args = parser.parse_args()
    if args.analyse:
        analyse(args.analyse)
    else:
        record(args)


if __name__ == "__main__":
    main()
