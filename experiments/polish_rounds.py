"""The polish (`registration.polish`) on the registered pictures of `registered_attacks.py`'s PNG row:
each picture's camera as registration hands it to the polish is captured once, then polished under
settings given on the command line and read with the polished camera (as `meshseal detect` reads it
before its second look), so that polish settings compare on the same starts in a minute or two.

    python experiments/polish_rounds.py capture --data data --start S --meshes 50 --out C.pt
    python experiments/polish_rounds.py read C.pt [C2.pt ...] [--set POLISH_ROUNDS=2 ...] [--jsonl OUT]
        [--from-truth] [--codec jpeg:75]

`capture` runs `evaluate_registered` (the pictures, views and messages of `registered_attacks.py
--start S --meshes N`: one seeded 256^2 view each, marked as `meshseal embed` marks, PNG) and keeps, for
each picture registration read, the picture, the object mask, the prepared original, the true camera
and the camera registration found (before the polish). `read` polishes each start with the module's
settings (`--set NAME=VALUE` overrides `meshseal.reading.registration` constants) and prints the share
detected at FPR 1e-6 and read exactly, the pose error (mean screen distance to the true camera's
surface points) at the start and after, and the polish's CPU seconds a picture; `--jsonl` writes one row a
picture. The p-value is the first reading's without the second look's Bonferroni factor (x2 or x3, the
same for every setting): the figures compare settings, not `meshseal detect`'s final rates, which
`registered_attacks.py` measures. `--from-truth` polishes from the true camera instead (how far the
polish's own minimum lies from it); `--codec` saves each picture through a codec first (the start is still
the PNG's registered camera).
Another code's polish reads the same captures through `PYTHONPATH` (its `src`
exported with `git archive`, e.g. commit 6eddc81's rounds, measured and reverted: docs/reading.md).
"""

from __future__ import annotations

import argparse
import ast
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def capture(args) -> None:
    import torch

    import meshseal.evaluation.evaluate as evaluate
    import meshseal.payload as payload
    import meshseal.reading.registration as registration
    from meshseal.api import load
    from meshseal.data.dataset import MeshDataset
    from meshseal.threads import configure
    from robust_curve import _Subset

    configure()
    model = load(args.model).model
    test = MeshDataset(args.data, "test")
    dataset = _Subset(test, list(range(args.start, min(args.start + args.meshes, len(test)))))
    # `evaluate_registered` reads each picture with its true camera first, then registered: the first
    # read tells which mesh the next registration belongs to and its camera, the polish's first call
    # within the registered read is the start to keep, and the message encoded names the mark.
    state = {"index": args.start - 1, "registering": False, "kept": False, "known": None}
    records, identities = {}, {}
    read, polish, encode = evaluate._read_or_none, registration.polish, payload.encode

    def kept_polish(mesh, camera, picture, mask):
        if state["registering"] and not state["kept"]:
            state["kept"] = True
            records[state["index"]] = {"mesh": mesh, "camera": camera, "picture": picture, "mask": mask,
                                       "known": state["known"]}
        return polish(mesh, camera, picture, mask)

    def watched_read(watermarker, picture, original, **options):
        if not options.get("register"):
            state["index"] += 1
            state["known"] = options["camera"]
            return read(watermarker, picture, original, **options)
        state["registering"], state["kept"] = True, False
        try:
            return read(watermarker, picture, original, **options)
        finally:
            state["registering"] = False
            if state["index"] in records:
                records[state["index"]] |= {"pixels": picture, "original": original}

    def named_encode(identity, *rest, **options):
        identities[state["index"] + 1] = identity
        return encode(identity, *rest, **options)

    registration.polish, evaluate._read_or_none, payload.encode = kept_polish, watched_read, named_encode
    torch.manual_seed(0)
    result = evaluate.evaluate_registered(model, dataset, len(dataset), args.seed, 256, "seed", None, views=1,
                                          register=True, attacks=[])
    for index, record in records.items():
        record["identity"] = identities[index]
    torch.save(records, args.out)
    print(f"{len(records)} starts kept in {args.out}; detected {result['tpr']:.2f} as `meshseal detect` reads them "
          f"(second look included), bit accuracy {result['bit_acc']:.3f}")


def read(args) -> None:
    import numpy as np
    import torch

    import meshseal.reading.registration as registration
    from meshseal.api import load
    from meshseal.threads import configure

    configure()
    for setting in args.set:
        name, value = setting.split("=", 1)
        if not hasattr(registration, name):
            sys.exit(f"polish_rounds: no setting {name} in meshseal.reading.registration")
        setattr(registration, name, ast.literal_eval(value))
    watermarker = load(args.model)
    records = {}
    for path in args.captures:
        records |= torch.load(path, weights_only=False)  # our own capture: cameras, meshes and tensors
    codec = None
    if args.codec:
        name, quality = args.codec.split(":")
        codec = (name.upper(), int(quality), 2 if name.upper() == "JPEG" else None)
    rows = []
    for index in sorted(records):
        record = records[index]
        picture, pixels = record["picture"], record["pixels"]
        if codec is not None:
            if tuple(picture.shape[-2:]) != pixels.shape[:2]:  # registered on an enlarged copy: left out
                continue
            pixels = _coded(pixels, codec)
            picture = torch.from_numpy(pixels).permute(2, 0, 1)[None].to(picture.dtype)
        started = time.process_time()
        camera = registration.polish(record["mesh"], record["known" if args.from_truth else "camera"], picture,
                                     record["mask"])
        seconds = time.process_time() - started
        decision = watermarker.decide([watermarker.read(pixels, record["original"], camera=camera)])
        rows.append({"mesh": index, "p": decision.p_value, "detected": bool(decision.detected),
                     "exact": decision.message == record["identity"], "seconds": seconds,
                     "pose_start": registration.pose_error(record["mesh"], record["known"], record["camera"], 256, 256),
                     "pose": registration.pose_error(record["mesh"], record["known"], camera, 256, 256)})
    if args.jsonl:
        Path(args.jsonl).write_text("".join(json.dumps(row) + "\n" for row in rows))
    mean = lambda key: float(np.mean([row[key] for row in rows]))  # noqa: E731
    median = lambda key: float(np.median([row[key] for row in rows]))  # noqa: E731
    print(f"{' '.join(args.set) or 'as shipped'}: {len(rows)} pictures, detected {mean('detected'):.3f}, exact "
          f"{mean('exact'):.3f}, pose error median {median('pose_start'):.3f} -> {median('pose'):.3f} px, "
          f"polish {mean('seconds'):.3f} CPU s a picture")


def _coded(pixels, codec):
    """(H, W, 3) float pixels in [0, 1] saved by `codec` (format, quality, subsampling) and read back."""
    import numpy as np

    from meshseal.reading.compression import _codec_round_trip

    saved = _codec_round_trip((np.clip(pixels, 0, 1) * 255).round().astype(np.uint8), codec)
    return saved.astype(np.float32) / 255


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    take = commands.add_parser("capture")
    take.add_argument("--data", type=Path, default=ROOT / "data")
    take.add_argument("--start", type=int, default=0)
    take.add_argument("--meshes", type=int, default=50)
    take.add_argument("--model", default="default")
    take.add_argument("--seed", type=int, default=0)
    take.add_argument("--out", required=True)
    again = commands.add_parser("read")
    again.add_argument("captures", nargs="+")
    again.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    again.add_argument("--model", default="default")
    again.add_argument("--jsonl")
    again.add_argument("--from-truth", action="store_true", help="polish from the true camera (where the polish's own minimum is)")
    again.add_argument("--codec", help="FORMAT:QUALITY (jpeg:75, webp:80): the picture saved so before the polish and the reading")
    args = parser.parse_args()
    sys.path.insert(0, str(ROOT / "experiments"))  # robust_curve's dataset slice
    (capture if args.command == "capture" else read)(args)


if __name__ == "__main__":
    main()
