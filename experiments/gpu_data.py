"""A dataset folder small enough to travel to a lent GPU (#48): the items of DATA whose textures are noise
or real images (the seed paper's protocol; what the blind G-buffer configs train on), with their meshes,
textures, manifest and splits. The device tool carries it when named in `carry` (about 50 MB).

python experiments/gpu_data.py --data data --out gpu_data
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from meshseal.data.build import write_manifest  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT / "data")
    parser.add_argument("--out", type=Path, default=ROOT / "gpu_data")
    parser.add_argument("--kinds", default="noise,real", help="texture kinds kept (comma-separated)")
    args = parser.parse_args()
    kinds = set(args.kinds.split(","))
    rows = [json.loads(line) for line in open(args.data / "manifest.jsonl")]
    kept = [row for row in rows if row["texture_kind"] in kinds]
    for sub in ("meshes", "textures"):
        (args.out / sub).mkdir(parents=True, exist_ok=True)
    for row in kept:
        for key in ("file", "texture_file"):
            if row.get(key) and (args.data / row[key]).exists():
                shutil.copy2(args.data / row[key], args.out / row[key])
    write_manifest(args.out, kept)
    if (args.data / "build_config.json").exists():
        shutil.copy2(args.data / "build_config.json", args.out / "build_config.json")
    print(f"{args.out}: {len(kept)} of {len(rows)} items "
          f"({sum(row['split'] == 'train' for row in kept)} train, {sum(row['split'] == 'test' for row in kept)} test)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
