"""Registered reading after a codec, with the registration comparing the picture with renders passed
through the picture's own codec or not (commit of this script: `registration.POLISH_CODEC` and
`TEXTURE_CODEC`, reverted by the next). The test pictures of `benchmarks/registration.py` (its `--work`
folder, made there first), saved with Pillow as JPEG or WebP at a quality, read registered (second look
included) and with the true camera; per picture: detected, p, the registered pose error (px).

    python experiments/registered_codec.py --data data --work /tmp/regbench --attack jpeg75 --start 0
        --meshes 50 --out LOG.jsonl [--plain]
    python experiments/registered_codec.py --summary LOG.jsonl [LOG2.jsonl]

`--plain`: both flags off (the registration as shipped before).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run(args) -> None:
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from meshseal.threads import configure

    configure()
    import numpy as np
    import torch
    from PIL import Image

    import meshseal
    import meshseal.reading.registration as registration
    from meshseal.data.dataset import MeshDataset
    from meshseal.render import Cameras, MeshBatch, compiled
    from registration import test_mesh  # benchmarks/registration.py

    if args.plain:
        registration.POLISH_CODEC = registration.TEXTURE_CODEC = False
    compiled.load()
    items = [i for i in json.loads((args.work / "index.json").read_text()) if i["kind"] == "test"]
    items = items[args.start:args.start + args.meshes]
    watermarker, dataset = meshseal.load(), MeshDataset(args.data, "test")
    pictures = args.work / "codec"
    pictures.mkdir(exist_ok=True)
    with open(args.out, "a") as log:
        for item in items:
            batch = test_mesh(dataset, item["mesh"])
            original = MeshBatch.from_tensors(*(batch[k] for k in ("positions", "normals", "uvs", "faces", "texture")))
            fmt, quality = ("JPEG", int(args.attack[4:])) if args.attack.startswith("jpeg") else ("WEBP", int(args.attack[4:]))
            path = pictures / f"{item['mesh']:03d}_{args.attack}.{'jpg' if fmt == 'JPEG' else 'webp'}"
            Image.open(item["picture"]).convert("RGB").save(path, format=fmt, quality=quality)
            c = item["camera"]
            truth = Cameras(torch.tensor([c["eye"]]), torch.tensor([c["at"]]), torch.tensor([c["up"]]), c["fov_y"],
                            principal=tuple(c["principal"]))
            row = {"mesh": item["mesh"], "attack": args.attack, "plain": args.plain}
            started = time.perf_counter()
            try:
                reading = watermarker.read(path, original, register=True)
                reading = watermarker.look_again(reading, original, None, None, True)
                found = watermarker.decide([reading])
                row |= {"registered": bool(found.detected), "p": float(found.p_value),
                        "pose": registration.pose_error(original, truth, reading.found, 256, 256)}
            except meshseal.MeshsealError as error:
                row |= {"registered": False, "error": str(error)[:80]}
            row["seconds"] = time.perf_counter() - started
            known = watermarker.decide([watermarker.read(path, original, camera=truth)])
            row |= {"known": bool(known.detected), "known_p": float(known.p_value)}
            bits = np.array([int(b) for b in known.bits])
            row["known_bits"] = float(np.mean(bits == np.array(item["bits"])))
            print(json.dumps(row), file=log, flush=True)


def summary(paths: list[Path]) -> None:
    for path in paths:
        rows = [json.loads(line) for line in path.read_text().splitlines()]
        poses = [r.get("pose", float("inf")) for r in rows]
        print(f"{path}: {len(rows)} pictures, detected registered {sum(r['registered'] for r in rows)}, "
              f"with the camera {sum(r['known'] for r in rows)}; pose error median {statistics.median(poses):.3f} px, "
              f"over 0.1 px {sum(p > 0.1 for p in poses)}; seconds median {statistics.median(r['seconds'] for r in rows):.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path)
    parser.add_argument("--work", type=Path, default=Path("/tmp/regbench"))
    parser.add_argument("--attack", default="jpeg75")
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--meshes", type=int, default=50)
    parser.add_argument("--out", type=Path)
    parser.add_argument("--plain", action="store_true")
    parser.add_argument("--summary", type=Path, nargs="+")
    args = parser.parse_args()
    if args.summary:
        summary(args.summary)
    else:
        run(args)


if __name__ == "__main__":
    main()
