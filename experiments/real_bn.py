"""Batch-norm statistics of a learned blind decoder measured on real renders of training meshes (#48).

A model trained on cached G-buffers keeps, in its decoder's batch norms, the statistics of baked views
(hard edges, one texture sample per frame pixel). `meshseal eval --protocol seed` reads pictures the
renderer made at 600 x 400 and framed (splatted edges, shrunk with antialiasing). This measures the
decoder's batch-norm statistics afresh (a cumulative average) on such pictures of TRAIN meshes (the test
split is never seen), then reads the test split in the paper's protocol with the old and the new
statistics (`training.batch_norm.decoder_statistics_from_renders`, what `train.bn_renders` does at the end of
a run, with the same seed). With --save, the model with the new statistics is written (its metadata kept).

python experiments/real_bn.py --model runs/NAME/model.safetensors --data data [--pictures 256] [--save OUT]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from meshseal.data.dataset import MeshDataset  # noqa: E402
from meshseal.models.io import load_model, read_metadata, save_model  # noqa: E402
from meshseal.training.batch_norm import decoder_statistics_from_renders  # noqa: E402
from meshseal.training.validate import evaluate  # noqa: E402

PAPER_SIZE = (400, 600)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--data", type=Path, default=ROOT / "data")
    parser.add_argument("--pictures", type=int, default=256)
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--skip-before", action="store_true", help="do not read the test split with the old statistics")
    parser.add_argument("--save", type=Path, default=None)
    args = parser.parse_args()
    kinds = ("noise", "real")
    model = load_model(args.model)
    test = MeshDataset(args.data, "test", seed=args.seed, texture_kinds=kinds)
    train = MeshDataset(args.data, "train", seed=args.seed, texture_kinds=kinds)
    result = {"model": str(args.model), "pictures": args.pictures}
    if not args.skip_before:
        before = evaluate(model, test, None, 1, args.seed, PAPER_SIZE, "seed")
        result["before"] = {k: before[k] for k in ("bit_acc", "bit_acc_std", "psnr_object")}
        print("before", json.dumps(result["before"]), flush=True)
    started = time.time()
    decoder_statistics_from_renders(model, train, args.pictures, PAPER_SIZE, "seed", seed=args.seed * 1_000_003 + 7,
                                    batch_size=args.batch)
    result["calibration_s"] = round(time.time() - started, 1)
    after = evaluate(model, test, None, 1, args.seed, PAPER_SIZE, "seed")
    result["after"] = {k: after[k] for k in ("bit_acc", "bit_acc_std", "psnr_object")}
    print("after", json.dumps(result["after"]), flush=True)
    if args.save:
        metadata = read_metadata(args.model)
        extra = {k: v for k, v in metadata.items() if k not in ("format", "config")}
        extra["batch_norm"] = f"decoder statistics from {args.pictures} seed-protocol renders of train meshes (experiments/real_bn.py)"
        save_model(model, args.save, extra)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
