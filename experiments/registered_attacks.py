"""The registered rows of `meshseal eval --register --attacks ...` on a slice of the test split, so that
100 meshes run as two processes on two cores: the test meshes [start, start + meshes), one seeded 256^2
view each, marked as `meshseal embed` marks (FLIP budget 0.03; `--strength S`: as `embed --strength S` marks), saved without metadata and read as
`meshseal detect` reads them (registered, second look), as PNG and after each picture attack; each
slice draws its own views and messages from the seed, so a slice's pictures are not those of a single
run over all meshes. `--merge` adds slices up: per attack the pictures, detected, exact, named, the
detected rate with the camera known (where the attack keeps the frame or is a central crop,
`evaluation.attacks.cropped_camera`) and the mean seconds; then the
detected rates by kind of picture (plain, magnified, minified, clipped, small).

    python experiments/registered_attacks.py --data data --start 0 --meshes 50 --json A.json
        [--attacks none,jpeg90,jpeg75,jpeg50,webp80,resize0.5,resize0.75,resize1.5,crop0.8,screenshot] [--strength S]
    python experiments/registered_attacks.py --merge A.json B.json

`--by-item` keeps each mesh's figures in the JSON (`by_item`: detected registered and, where the
attack keeps the frame, with the camera known), so that the pictures registration loses can be named.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ATTACKS = "none,jpeg90,jpeg75,jpeg50,webp80,resize0.5,resize0.75,resize1.5,crop0.8,screenshot"
FIELDS = ("detected", "exact", "named", "bit_acc")


def run(args) -> None:
    import torch

    from meshseal.api import load
    from meshseal.data.dataset import MeshDataset
    from meshseal.evaluation.attacks import parse
    from meshseal.evaluation.evaluate import evaluate_registered
    from meshseal.threads import configure
    from robust_curve import _Subset  # a slice of a dataset, as `evaluate_registered` takes one

    configure()
    model = load(args.model).model
    test = MeshDataset(args.data, "test")
    dataset = _Subset(test, list(range(args.start, min(args.start + args.meshes, len(test)))))
    torch.manual_seed(0)
    attacks = [name for name in parse(args.attacks) if name != "none"]
    louder = {} if args.strength is None else {"strength": args.strength, "max_flip": None}  # as `embed --strength`
    result = evaluate_registered(model, dataset, len(dataset), args.seed, 256, "seed", None, views=1,
                                 register=True, attacks=attacks, by_item=args.by_item, **louder)
    rows = {"none": {"pictures": result["n_meshes"], "detected": result["tpr"], "exact": result["exact_message"],
                     "named": result["tpr_message_named"], "bit_acc": result["bit_acc"],
                     "detected_known_camera": result["tpr_known_camera"], "seconds": result["seconds_per_picture"]}}
    for name, entry in result.get("attacks", {}).items():
        rows[name] = {"pictures": entry["pictures"], "seconds": entry["seconds"],
                      "detected_known_camera": entry.get("detected_known_camera"),
                      "pose_error_px_median": entry.get("pose_error_px_median")} | {k: entry[k] for k in FIELDS}
    payload = {"start": args.start, "meshes": len(dataset), "strength": args.strength, "rows": rows,
               "by_kind": result.get("by_kind", {}), "by_item": result.get("by_item", {}),
               "visibility": {key: result.get(key) for key in ("flip_object", "flip_object_p95", "psnr_object",
                                                               "psnr_texture_shown")}}
    Path(args.json).write_text(json.dumps(payload, indent=1))
    print(json.dumps(payload))


def merge(paths: list[str]) -> None:
    """Per attack over the slices: pictures, then each rate weighted by its slice's pictures."""
    slices = [json.loads(Path(path).read_text()) for path in paths]
    names = list(dict.fromkeys(name for part in slices for name in part["rows"]))
    spans = ", ".join(f"{part['start']}-{part['start'] + part['meshes'] - 1}" for part in slices)
    print(f"<!-- test meshes: {spans} -->")
    strengths = {part.get("strength") for part in slices}
    seen = [part["visibility"] for part in slices if part.get("visibility", {}).get("flip_object") is not None]
    if seen:
        weights = [part["meshes"] for part in slices if part.get("visibility", {}).get("flip_object") is not None]
        average = lambda key: sum(v[key] * w for v, w in zip(seen, weights)) / sum(weights)  # noqa: E731
        print(f"strength {', '.join('budget' if s is None else f'{s:g}' for s in strengths)}: object FLIP "
              f"{average('flip_object'):.4f} (p95 of the slices' {max(v['flip_object_p95'] for v in seen):.4f}), "
              f"object PSNR {average('psnr_object'):.1f} dB, texture PSNR {average('psnr_texture_shown'):.1f} dB "
              f"over the shown texels\n")
    print("| attack | pictures | detected | exact | named | bit accuracy | detected, camera known | seconds a picture |")
    print("|---|---|---|---|---|---|---|---|")
    for name in names:
        parts = [part["rows"][name] for part in slices if name in part["rows"]]
        count = sum(part["pictures"] for part in parts)
        mean = lambda key: sum(part[key] * part["pictures"] for part in parts) / count  # noqa: E731
        known = [part for part in parts if part.get("detected_known_camera") is not None]
        known_text = f"{sum(p['detected_known_camera'] * p['pictures'] for p in known) / sum(p['pictures'] for p in known):.2f}" \
            if known and len(known) == len(parts) else "-"
        print(f"| {name} | {count} | {mean('detected'):.2f} | {mean('exact'):.2f} | {mean('named'):.2f} | "
              f"{mean('bit_acc'):.3f} | {known_text} | {mean('seconds'):.1f} |")
    kinds = list(dict.fromkeys(kind for part in slices for kind in part.get("by_kind", {})))
    if not kinds:
        return
    print("\nDetected by kind of picture (`meshseal eval`'s kinds: a picture can be of several):\n")
    print("| kind | pictures | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for kind in kinds:
        parts = [part["by_kind"][kind] for part in slices if kind in part.get("by_kind", {})]
        count = sum(part["pictures"] for part in parts)
        cells = []
        for name in names:
            key = "detected" if name == "none" else name
            have = [part for part in parts if part.get(key) is not None]
            cells.append(f"{sum(p[key] * p['pictures'] for p in have) / sum(p['pictures'] for p in have):.2f}" if have else "-")
        print(f"| {kind} | {count} | " + " | ".join(cells) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT / "data")
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--meshes", type=int, default=50)
    parser.add_argument("--attacks", default=ATTACKS)
    parser.add_argument("--model", default="default")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--strength", type=float, default=None,
                        help="mark at this strength as `meshseal embed --strength` does (no FLIP budget); "
                             "not given: strength 1 within the FLIP budget, as `embed` marks")
    parser.add_argument("--by-item", action="store_true",
                        help="also each mesh's figures (`by_item`: detected registered and with the camera, per attack)")
    parser.add_argument("--json", default=None)
    parser.add_argument("--merge", nargs="+", default=None)
    args = parser.parse_args()
    if args.merge:
        merge(args.merge)
    else:
        if not args.json:
            parser.error("--json OUT is needed to run a slice")
        run(args)


if __name__ == "__main__":
    main()
