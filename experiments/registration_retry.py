"""Registration settings side by side on the same pictures: its retry (`register.RETRY_ABOVE`,
`RETRY_KEEP`, `RETRY_ANGLE`: more candidate views where the texture still fits poorly after the first
pass) and the second look's threshold (`api.LOOK_AGAIN_BELOW`).

Every `--stride`-th mesh of a split (the train split by default: the retry was shaped on test pictures),
the k-th one drawn seeded `--seed` + k, is marked as `registration_conditions.py` marks it (an
error-corrected ID, the shipped default; `--unmarked`: the original, for the time a picture without a
mark costs and its false detections), seen from one seeded view at 256^2 on a plain random background,
saved as 8-bit values, and read as `meshseal detect --mesh` reads it under each setting (`--setting
NAME=ABOVE,KEEP,ANGLE[,LOOK]`; default: the retry off and the shipped setting); the true camera's
reading is the reference. Prints per-mesh changes and one summary row per setting: bit accuracy,
registration success (pose error < 0.5 px or IoU >= 0.95), detection rate at FPR 1e-6, seconds per
picture. Several processes can share the work (`--worker K --workers N`, one JSONL each;
`--summarize` reads them).

    python experiments/registration_retry.py --data data --stride 4 --jsonl runs/retry.jsonl
    python experiments/registration_retry.py --data data --split test --stride 1 --setting first=0.4,8,15 --setting now=0.2,12,12
    python experiments/registration_retry.py --summarize runs/retry*.jsonl
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

import meshseal
from meshseal import api, payload
from meshseal import register as registration
from meshseal.data.dataset import MeshDataset, collate
from meshseal.pipeline import batch_mark_grid, batch_texels_used, sample_views
from meshseal.register import pose_error
from meshseal.render import MeshBatch, MeshRenderer
from registration_conditions import background_for  # experiments/registration_conditions.py

SHIPPED = (registration.RETRY_ABOVE, registration.RETRY_KEEP, registration.RETRY_ANGLE, api.LOOK_AGAIN_BELOW)
SETTINGS = {"off": (SHIPPED[0], 0, *SHIPPED[2:]), "on": SHIPPED}  # name: (RETRY_ABOVE, RETRY_KEEP, RETRY_ANGLE, LOOK_AGAIN_BELOW)


def parse_setting(text: str) -> tuple[str, tuple[float, int, float, float]]:
    """NAME=ABOVE,KEEP,ANGLE[,LOOK] (register's RETRY_ABOVE, RETRY_KEEP, RETRY_ANGLE; api's LOOK_AGAIN_BELOW)."""
    name, _, values = text.partition("=")
    above, keep, angle, *look = values.split(",")
    return name, (float(above), int(keep), float(angle), float(look[0]) if look else SHIPPED[3])


def use(setting: tuple[float, int, float, float]) -> None:
    registration.RETRY_ABOVE, registration.RETRY_KEEP, registration.RETRY_ANGLE, api.LOOK_AGAIN_BELOW = setting


def picture(model, batch, seed: int, marked: bool = True):
    """The marked (or the original) mesh's 8-bit picture (256, 256, 3) float, its true camera, the
    original and the message."""
    positions, normals, uvs, faces, texture = (batch[k] for k in ("positions", "normals", "uvs", "faces", "texture"))
    generator = torch.Generator().manual_seed(seed)
    identity = int(torch.randint(0, 2 ** 31, (1,), generator=generator))
    message = payload.encode(identity, None, model.n_bits)[None]
    with torch.no_grad():
        shown = model.mark_texture(texture, message, 1.0, payload.key_seed(None), batch_mark_grid(model, batch),
                                   batch_texels_used(batch)) if marked else texture
        cameras, lights = sample_views(1, "seed", generator)
        out = MeshRenderer()(MeshBatch.from_tensors(positions, normals, uvs, faces, shown), cameras, lights, 256, 256,
                             torch.zeros(1, 3))
        alpha = out.rgba[0, ..., 3][None]
        composed = (out.image[0] + (1 - alpha) * background_for("plain", 256, generator, [])).clamp(0, 1)
    pixels = (composed.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8).astype(np.float32) / 255
    return pixels, cameras, MeshBatch.from_tensors(positions, normals, uvs, faces, texture), message


def read(wm, pixels, original, message, cameras, register: bool) -> dict:
    """One reading as `meshseal detect --mesh` makes it (or with the true camera): bits right, pose, IoU."""
    started = time.perf_counter()
    try:
        reading = wm.read(pixels, original, register=True) if register else wm.read(pixels, original, camera=cameras)
        reading = wm.look_again(reading, original) if register else reading
    except meshseal.MeshsealError:
        reading = None
    seconds = time.perf_counter() - started
    if reading is None:
        return {"bits": 0.5, "pose": float("inf"), "iou": 0.0, "detected": False, "seconds": seconds}
    decision = wm.decide([reading])
    return {"bits": float(np.mean([int(b) for b in decision.bits] == message[0].numpy())),
            "pose": pose_error(original, cameras, reading.found, 256, 256) if register else 0.0,
            "iou": reading.registration_iou or 1.0, "detected": bool(decision.detected), "seconds": seconds}


def summarize(rows: list[dict]) -> None:
    names = [name for name in rows[0] if name not in ("mesh", "known")] if rows else []
    rows = [row for row in rows if all(name in row for name in names)]
    for row in rows:
        first = row[names[0]]
        for name in names[1:]:
            other = row[name]
            if abs(first["bits"] - other["bits"]) > 1e-3 or abs(first["pose"] - other["pose"]) > 0.05:
                print(f"mesh {row['mesh']} {names[0]} -> {name}: bits {first['bits']:.3f} -> {other['bits']:.3f}, "
                      f"pose {first['pose']:.2f} -> {other['pose']:.2f} px")
    count = len(rows)
    print(f"{count} pictures; true camera: bit accuracy {np.mean([r['known']['bits'] for r in rows]):.4f}")
    print("| retry | bit acc. registered | registration success | detected (FPR 1e-6) | s / picture |")
    print("|---|---|---|---|---|")
    for name in names:
        group = [r[name] for r in rows]
        success = np.mean([(g["pose"] < 0.5) or (g["iou"] >= 0.95) for g in group])
        print(f"| {name} | {np.mean([g['bits'] for g in group]):.4f} | {success:.3f} | "
              f"{np.mean([g['detected'] for g in group]):.3f} | {np.mean([g['seconds'] for g in group]):.2f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path)
    parser.add_argument("--split", default="train")
    parser.add_argument("--stride", type=int, default=4, help="every N-th mesh of the split")
    parser.add_argument("--first", type=int, default=None, help="only the first N meshes drawn")
    parser.add_argument("--worker", type=int, default=0)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--seed", type=int, default=7000)
    parser.add_argument("--jsonl", type=Path, default=None, help="one JSON line per picture")
    parser.add_argument("--summarize", type=Path, nargs="+", default=None, help="JSONL files of earlier runs")
    parser.add_argument("--unmarked", action="store_true",
                        help="pictures of the original (the time an unmarked picture costs; its false detections)")
    parser.add_argument("--setting", type=parse_setting, action="append", default=None,
                        help="NAME=ABOVE,KEEP,ANGLE[,LOOK]: a setting to compare (default: the retry off and the shipped one)")
    args = parser.parse_args()
    if args.summarize:
        summarize([json.loads(line) for path in args.summarize for line in path.read_text().splitlines() if line])
        return
    wm = meshseal.load()
    dataset = MeshDataset(args.data, args.split)
    log = args.jsonl.open("a") if args.jsonl else None
    settings = dict(args.setting) if args.setting else SETTINGS
    rows = []
    for drawn, index in list(enumerate(range(0, len(dataset), args.stride)))[:args.first][args.worker::args.workers]:
        pixels, cameras, original, message = picture(wm.model, collate([dataset[index]], "cpu"), args.seed + drawn,
                                                       marked=not args.unmarked)
        row = {"mesh": index, "known": read(wm, pixels, original, message, cameras, register=False)}
        for name, setting in settings.items():
            use(setting)
            row[name] = read(wm, pixels, original, message, cameras, register=True)
        use(SHIPPED)
        rows.append(row)
        if log:
            log.write(json.dumps(row) + "\n")
            log.flush()
    summarize(rows)


if __name__ == "__main__":
    main()
