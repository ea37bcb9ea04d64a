"""Reading pictures users actually have, without metadata: the issue's list of conditions, each
measured on the same test meshes.

For the first N test meshes (or train meshes, `--split train`) (one seeded view each, the paper's camera and light ranges) the shipped
default marks the texture with an error-corrected ID; the picture is rendered by our renderer and read
as `meshseal detect --mesh` reads it (object found from the background, camera registered), under:
plain (a plain random background, 256^2: the reference), gradient (a linear ramp between two random
colours), busy (a real texture image from the dataset as the background), cut (the camera aimed off
the object so that the frame edge cuts part of it off), 512, 1024 and 2048 (larger pictures), jpeg75 (JPEG
quality 75). Per condition: pictures `meshseal detect` refuses (no object found), registration
success (pose error < 0.5 px at the picture's size scaled to 256^2, or IoU >= 0.95), median pose
error, bit accuracy with the registered and with the true camera, detection rate at FPR 1e-6, and
seconds per picture. A refused picture counts as read at chance.

    python experiments/registration_conditions.py --data data --meshes 20
        [--conditions plain gradient busy cut 512 1024 jpeg75] [--split train]
"""

from __future__ import annotations

import argparse
import io
import json
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

import meshseal
from meshseal import payload
from meshseal.data.dataset import MeshDataset, collate
from meshseal.methods.batches import batch_mark_grid, batch_texels_used
from meshseal.training.views import random_backgrounds
from meshseal.render.views import sample_views
from meshseal.reading.registration import pose_error
from meshseal.render import MeshBatch, MeshRenderer

CONDITIONS = ("plain", "gradient", "busy", "cut", "512", "1024", "2048", "jpeg75")


def background_for(condition: str, size: int, generator: torch.Generator, textures: list[Path]) -> torch.Tensor:
    """(3, size, size) background of the condition."""
    if condition == "gradient":
        a, b = torch.rand(3, generator=generator), torch.rand(3, generator=generator)
        ramp = torch.linspace(0, 1, size)
        angle = float(torch.rand(1, generator=generator)) * 2 * np.pi
        reach = abs(np.cos(angle)) + abs(np.sin(angle))
        t = ((np.cos(angle) * ramp[None, :] + np.sin(angle) * ramp[:, None]) / reach + 1) / 2
        return a[:, None, None] * (1 - t) + b[:, None, None] * t
    if condition == "busy":
        path = textures[int(torch.randint(len(textures), (1,), generator=generator))]
        with Image.open(path) as image:
            pixels = np.asarray(image.convert("RGB").resize((size, size), Image.BILINEAR), dtype=np.float32) / 255
        return torch.from_numpy(pixels).permute(2, 0, 1)
    return random_backgrounds(1, generator)[0][:, None, None].expand(3, size, size)


def aimed_off(cameras, generator: torch.Generator):
    """The cameras turned so the object sits at a frame edge, partly cut off (a random side)."""
    forward = F.normalize(cameras.at - cameras.eye, dim=-1)
    right = F.normalize(torch.cross(forward, cameras.up, dim=-1), dim=-1)
    up = torch.cross(right, forward, dim=-1)
    angle = float(torch.rand(1, generator=generator)) * 2 * np.pi
    shift = 1.5 * (np.cos(angle) * right + np.sin(angle) * up)
    return type(cameras)(cameras.eye, cameras.at + shift, cameras.up, cameras.fov_y)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--model", default="default", help="shipped model name or .safetensors path")
    parser.add_argument("--meshes", type=int, default=20)
    parser.add_argument("--conditions", nargs="+", default=list(CONDITIONS), choices=CONDITIONS)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--split", default="test", choices=("train", "test"), help="the meshes' split (default test)")
    parser.add_argument("--jsonl", type=Path, default=None, help="one JSON line per picture")
    args = parser.parse_args()
    wm = meshseal.load(args.model)
    model = wm.model
    dataset = MeshDataset(args.data, args.split)
    textures = sorted((args.data / "textures").glob("*.png"))
    renderer = MeshRenderer()
    rows = {condition: [] for condition in args.conditions}
    log = args.jsonl.open("w") if args.jsonl else None
    for index in range(min(args.meshes, len(dataset))):
        batch = collate([dataset[index]], "cpu")
        positions, normals, uvs, faces, texture = (batch[k] for k in ("positions", "normals", "uvs", "faces", "texture"))
        original = MeshBatch.from_tensors(positions, normals, uvs, faces, texture)
        for condition in args.conditions:
            generator = torch.Generator().manual_seed(args.seed * 100003 + index)
            identity = int(torch.randint(0, 2 ** 31, (1,), generator=generator))
            message = payload.encode(identity, None, model.n_bits)[None]
            size = int(condition) if condition.isdigit() else 256
            with torch.no_grad():
                marked = model.texture_encoder(texture, message, 1.0, payload.key_seed(None), batch_mark_grid(model.texture_encoder, batch),
                                            batch_texels_used(batch))
                cameras, lights = sample_views(1, "seed", generator)
                if condition == "cut":
                    cameras = aimed_off(cameras, generator)
                out = renderer(MeshBatch.from_tensors(positions, normals, uvs, faces, marked), cameras, lights, size, size,
                               torch.zeros(1, 3))
                alpha = out.rgba[0, ..., 3][None]
                picture = (out.image[0] + (1 - alpha) * background_for(condition, size, generator, textures)).clamp(0, 1)
            array = (picture.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)
            buffer = io.BytesIO()
            Image.fromarray(array).save(buffer, format="JPEG" if condition == "jpeg75" else "PNG", quality=75)
            buffer.seek(0)
            pixels = np.asarray(Image.open(buffer).convert("RGB"), dtype=np.float32) / 255
            started = time.perf_counter()
            try:
                reading = wm.look_again(wm.read(pixels, original, register=True), original)  # as `meshseal detect`
            except meshseal.MeshsealError:
                reading = None
            seconds = time.perf_counter() - started
            try:
                known = wm.read(pixels, original, camera=cameras)
            except meshseal.MeshsealError:
                known = None
            agree = lambda r: 0.5 if r is None else float(np.mean(  # noqa: E731
                [int(b) for b in wm.decide([r]).bits] == message[0].numpy()))
            pose = float("inf") if reading is None else pose_error(original, cameras, reading.found, size, size) * 256 / size
            row = {"mesh": index, "condition": condition, "refused": reading is None, "pose_px_256": pose,
                   "iou": 0.0 if reading is None else reading.registration_iou, "bit_acc": agree(reading),
                   "bit_acc_known": agree(known), "seconds": seconds,
                   "detected": reading is not None and bool(wm.decide([reading]).detected)}
            rows[condition].append(row)
            if log:
                log.write(json.dumps(row) + "\n")
                log.flush()
            print(f"mesh {index} {condition:8s} pose {pose:7.2f} px bits {row['bit_acc']:.3f} (known {row['bit_acc_known']:.3f}) "
                  f"{seconds:.1f} s{' REFUSED' if row['refused'] else ''}", flush=True)
    print("| condition | pictures | refused | registration success | median pose (px at 256^2) | bit acc. registered | "
          "bit acc. true camera | detected (FPR 1e-6) | s / picture |")
    print("|---|---|---|---|---|---|---|---|---|")
    for condition, group in rows.items():
        mean = lambda key: float(np.mean([r[key] for r in group]))  # noqa: E731
        success = np.mean([(r["pose_px_256"] < 0.5) or (r["iou"] >= 0.95) for r in group])
        print(f"| {condition} | {len(group)} | {sum(r['refused'] for r in group)} | {success:.2f} | "
              f"{np.median([r['pose_px_256'] for r in group]):.2f} | {mean('bit_acc'):.3f} | {mean('bit_acc_known'):.3f} | "
              f"{mean('detected'):.2f} | {mean('seconds'):.1f} |")


if __name__ == "__main__":
    main()
