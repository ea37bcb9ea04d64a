"""One line per picture read, so that the misses of a class can be looked at one by one: the first N test
meshes, one seeded 256^2 view each, marked by a spread model at full strength (no FLIP budget) and read with
the camera known, as `experiments/robust_curve.py` reads them, as PNG and after each attack. Each JSON
line: the mesh's index and id, the attack, the object's pixels, the picture's kinds
(`evaluation.evaluate.picture_kinds`), the grid the mesh is marked on, the any-mark p-value, detected at
1e-6, and the pilot's z on each grid read (`models.spread.pilot_z`). A summary by kind closes the run.

    python experiments/picture_log.py --data data --meshes 100 --attacks none,jpeg90 --out LOG.jsonl
        [--config configs/default.yaml] [--set KEY=VALUE ...]
    python experiments/picture_log.py --show LOG.jsonl --kind small [--attack none]
    python experiments/picture_log.py --summary LOG.jsonl   # by kind and attack: detected, pilot z, z / PNG z
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def hook_readings(order: list[str], handle) -> None:
    """Make `meshseal.evaluation.evaluate` call handle(state, watermarker, reading, attack) after each
    picture it reads (`reading` None where nothing was read), `attack` named from `order` (the eval
    reads each picture with its camera first, then after each attack); `state` holds the mesh's index
    (from 0), its object pixels, its picture kinds and the grid it is marked on."""
    from meshseal.evaluation import evaluate as ev

    state = {"mesh": -1, "call": 0}
    real_kinds, real_read = ev.picture_kinds, ev._read_or_none

    def kinds(encoder, grid, pictures, masks, *rest):  # called once per mesh, before its readings
        state.update(mesh=state["mesh"] + 1, call=0, pixels=int(masks[0].sum()), grid=grid)
        state["kinds"] = real_kinds(encoder, grid, pictures, masks, *rest)
        return state["kinds"]

    def read(watermarker, picture, original, **options):
        reading = real_read(watermarker, picture, original, **options)
        attack = order[state["call"]] if state["call"] < len(order) else "?"
        state["call"] += 1
        handle(state, watermarker, reading, attack)
        return reading

    ev.picture_kinds, ev._read_or_none = kinds, read


def record(args) -> None:
    import torch
    import yaml

    from meshseal.data.dataset import MeshDataset
    from meshseal.evaluation import evaluate as ev
    from meshseal.evaluation.attacks import parse
    from meshseal.models import ModelConfig, WatermarkModel
    from meshseal.models.spread import pilot_z, split_grids

    config = yaml.safe_load(args.config.read_text())["model"]
    for item in args.set:
        key, value = item.split("=", 1)
        config[key] = yaml.safe_load(value)
    model = WatermarkModel(ModelConfig.from_dict(config))
    dataset = MeshDataset(args.data, "test", seed=0)
    attacks = parse(args.attacks)
    order = ["png"] + list(attacks)  # the eval reads each picture with its camera first, then after each attack
    out = open(args.out, "w")

    def handle(state, watermarker, reading, attack):
        line = {"mesh": state["mesh"], "id": dataset.rows[state["mesh"]]["id"], "attack": attack,
                "pixels": state["pixels"], "kinds": state["kinds"][0], "grid": state["grid"]}
        if reading is not None:
            decision = watermarker.decide([reading])
            method = watermarker.method
            evidence = reading.evidence if reading.evidence.dim() == 2 else reading.evidence[None]
            line |= {"p": decision.p_value, "detected": bool(decision.detected),
                     "pilot_z": [round(float(pilot_z(method.encoder, sums[0].double(), method.key_seed(None))[0]), 2)
                                 for sums in split_grids(method.encoder, evidence)]}
        out.write(json.dumps(line) + "\n")
        out.flush()

    hook_readings(order, handle)
    torch.manual_seed(0)
    result = ev.evaluate_registered(model, dataset, args.meshes, 0, 256, "seed", None, views=1, register=False,
                                    max_flip=None, attacks=attacks)
    print(json.dumps(result.get("by_kind")))


def _lines(path) -> list[dict]:
    """The JSON lines of a log `record` wrote."""
    return [json.loads(text) for text in Path(path).read_text().splitlines() if text.strip()]


def show(args) -> None:
    lines = _lines(args.show)
    chosen = [line for line in lines if line["attack"] == args.attack and (not args.kind or args.kind in line["kinds"])]
    for line in sorted(chosen, key=lambda line: line["pixels"]):
        p = line.get("p")
        print(f"{line['mesh']:4d} {line['id'][:40]:40s} {line['pixels']:6d} px {','.join(line['kinds']):18s} grid {line['grid']:4d} "
              f"{'detected' if line.get('detected') else 'missed  '} p {p if p is None else f'{p:.1e}'} pilot z {line.get('pilot_z')}")


def summary(path: str) -> None:
    """By kind and attack: pictures, detected, the pilot's z (the larger over the grids read) at its
    quartiles, and the median of each picture's z over its own PNG z."""
    import numpy as np

    lines = _lines(path)
    png = {line["mesh"]: max(line["pilot_z"]) for line in lines if line["attack"] == "png" and line.get("pilot_z")}
    print("| kind | attack | pictures | detected | pilot z p25 / p50 / p75 | z / PNG z, median |\n|---|---|---|---|---|---|")
    kinds = sorted({kind for line in lines for kind in line["kinds"]})
    attacks = list(dict.fromkeys(line["attack"] for line in lines if line["attack"] != "none"))
    for kind in kinds:
        for attack in attacks:
            chosen = [line for line in lines if line["attack"] == attack and kind in line["kinds"]]
            z = np.array([max(line["pilot_z"]) for line in chosen if line.get("pilot_z")])
            ratio = [max(line["pilot_z"]) / png[line["mesh"]] for line in chosen
                     if line.get("pilot_z") and png.get(line["mesh"], 0) > 0]
            if len(z):
                q = np.quantile(z, [0.25, 0.5, 0.75])
                print(f"| {kind} | {attack} | {len(chosen)} | {np.mean([bool(line.get('detected')) for line in chosen]):.2f} | "
                      f"{q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f} | {np.median(ratio):.2f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT / "data")
    parser.add_argument("--meshes", type=int, default=100)
    parser.add_argument("--attacks", default="none,jpeg90")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--config", type=Path, default=ROOT / "configs" / "default.yaml")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--show", default=None, help="a log this script wrote: print its pictures, smallest first")
    parser.add_argument("--summary", default=None, help="a log this script wrote: a table by kind and attack")
    parser.add_argument("--kind", default=None, help="with --show: only pictures of this kind")
    parser.add_argument("--attack", default="png", help="with --show: this attack's readings (png: as rendered)")
    args = parser.parse_args()
    if args.summary:
        summary(args.summary)
    elif args.show:
        show(args)
    elif args.out is None:
        parser.error("--out LOG.jsonl is needed to record")
    else:
        record(args)


if __name__ == "__main__":
    main()
