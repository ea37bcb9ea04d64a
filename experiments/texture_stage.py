"""Registration's texture stage alone: from the true camera and from one about a pixel off, how close
does it end, with the light fitted on all of the object's pixels, on its flattest half, and with both
runs and the pick between them (`register.refine_on_texture_twice`, what `meshseal detect` runs)?

For test meshes START .. START+N-1: the same pictures as `registration_candidates.py` (the shipped mark,
one seeded 256^2 view, 8-bit values, plain random background, object found from the background). One
JSON line per picture with the final pose errors (pixels at 256^2), then a summary line: the share of
pictures ending under 0.5 px for each variant, and the mean seconds of the two-run stage. `--retry R`
sets `register.FLAT_RETRY` (0: the flat-half run always follows).

    python experiments/texture_stage.py --data data [--start 0] [--meshes 100] [--jitter 1.0] [--retry R]
"""

from __future__ import annotations

import argparse
import json
import time

import torch
from registration_candidates import seeded_picture

import meshseal
from meshseal import register as registration
from meshseal.data.dataset import MeshDataset
from meshseal.pipeline import jitter_cameras


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--meshes", type=int, default=100)
    parser.add_argument("--jitter", type=float, default=1.0, help="pixels (at 256^2) of the start's error")
    parser.add_argument("--retry", type=float, default=registration.FLAT_RETRY)
    args = parser.parse_args()
    registration.FLAT_RETRY = args.retry
    model = meshseal.load().model
    dataset = MeshDataset(args.data, "test")
    rows = []
    for index in range(args.start, min(len(dataset), args.start + args.meshes)):
        original, cameras, picture, mask, _ = seeded_picture(model, dataset, index)
        mask = torch.from_numpy(mask)[None].float()
        start = jitter_cameras(cameras, args.jitter, 256, torch.Generator().manual_seed(index))
        error = lambda camera: round(registration.pose_error(original, cameras, camera, 256, 256), 3)  # noqa: E731
        started = time.perf_counter()
        twice = registration.refine_on_texture_twice(original, start, picture, mask)
        row = {"mesh": index, "id": dataset.rows[index]["id"], "start_px": error(start),
               "twice_seconds": round(time.perf_counter() - started, 2), "twice_px": error(twice),
               "all_px": error(registration.refine_on_texture(original, start, picture, mask, light_from="all")),
               "flat_px": error(registration.refine_on_texture(original, start, picture, mask, light_from="flat")),
               "twice_from_truth_px": error(registration.refine_on_texture_twice(original, cameras, picture, mask))}
        rows.append(row)
        print(json.dumps(row), flush=True)
    share = {key: round(sum(r[key] < 0.5 for r in rows) / len(rows), 3)
             for key in ("start_px", "all_px", "flat_px", "twice_px", "twice_from_truth_px")}
    seconds = round(sum(r["twice_seconds"] for r in rows) / len(rows), 2)
    print(json.dumps({"pictures": len(rows), "under_0.5_px": share, "twice_seconds": seconds, "retry": args.retry}))


if __name__ == "__main__":
    main()
