"""Why pictures whose camera an attack moved (crops, resizing) read worse than the same pictures whole:
each of the first N test meshes is marked (strength 1), rendered from one seeded 256^2 view, put through
one geometric attack, and read three ways: with the attacked picture's true camera (the attack's own
intrinsics), registered, and registered then looked at again (as `meshseal detect`). One line a
picture: bit accuracy, -log10 p, and the registered camera's pose error against the true one.

    python experiments/geometric_diag.py --data data --meshes 10 --attack crop0.8 [--model default] [--fov 40]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time

import numpy as np
import torch

from meshseal import payload
from meshseal.api import load
from meshseal.data.dataset import MeshDataset, collate
from meshseal.evaluation.attacks import apply as attack_picture
from meshseal.methods.batches import batch_mark_grid, batch_texels_used, charted_item
from meshseal.reading.registration import crop_intrinsics, pose_error
from meshseal.render import MeshBatch, MeshRenderer
from meshseal.render.views import sample_views
from meshseal.training.views import random_backgrounds


def true_camera(camera, attack: str, height: int, width: int):
    """The camera of the attacked picture (crop and resize only; other attacks keep it) and its size."""
    if attack.startswith("crop"):
        keep = float(attack[4:])
        h, w = max(8, round(height * keep)), max(8, round(width * keep))
        top, left = (height - h) // 2, (width - w) // 2
        # the crop as a (rectangular) window: fov over its height, principal point shifted
        box = (left + w / 2, top + h / 2, h / 2)
        fov, principal = crop_intrinsics(height, width, box, float(camera.fov_y))
        principal = (principal[0] * h / w, principal[1])
        return dataclasses.replace(camera, fov_y=fov, principal=principal), h, w
    if attack.startswith("resize"):
        factor = float(attack[6:])
        return camera, max(8, round(height * factor)), max(8, round(width * factor))
    return camera, height, width


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--meshes", type=int, default=10)
    parser.add_argument("--attack", default="crop0.8")
    parser.add_argument("--model", default="default")
    parser.add_argument("--fov", type=float, default=None,
                        help="render with this vertical field of view (registration assumes 60 degrees)")
    args = parser.parse_args()
    wm = load(args.model)
    model = wm.model
    dataset = MeshDataset(args.data, "test", seed=0)
    renderer = MeshRenderer()
    generator = torch.Generator().manual_seed(2_000_003)
    for index in range(args.meshes):
        batch = charted_item(collate([dataset[index]]))
        identity = int(torch.randint(0, 2 ** 31, (1,), generator=generator))
        message = payload.encode(identity, None, model.n_bits)[None]
        positions, normals, uvs, faces, texture = (batch[k] for k in ("positions", "normals", "uvs", "faces", "texture"))
        with torch.no_grad():
            grid, used = batch_mark_grid(model.texture_encoder, batch), batch_texels_used(batch)
            marked = model.texture_encoder(texture, message, 1.0, payload.key_seed(None), grid, used)
            cameras, lights = sample_views(1, "seed", generator)
            if args.fov is not None:  # the same framing through another lens: the eye moved to keep the object's size
                scale = math.tan(math.radians(cameras.fov_y) / 2) / math.tan(math.radians(args.fov) / 2)
                cameras = dataclasses.replace(cameras, fov_y=args.fov, eye=cameras.at + (cameras.eye - cameras.at) * scale)
            background = random_backgrounds(1, generator)
            picture = renderer(MeshBatch.from_tensors(positions, normals, uvs, faces, marked), cameras, lights, 256, 256,
                               background).image.clamp(0, 1)
        original = MeshBatch.from_tensors(positions, normals, uvs, faces, texture)
        picture8 = np.round(picture[0].permute(1, 2, 0).numpy() * 255).astype(np.uint8)
        hit = attack_picture(args.attack, picture8, np.random.default_rng([0, index])).astype(np.float32) / 255
        camera, h, w = true_camera(cameras[[0]], args.attack, 256, 256)
        out = []
        for how in ("true", "registered", "again"):
            started = time.perf_counter()
            try:
                if how == "true":
                    reading = wm.read(hit, original, camera=camera)
                else:
                    reading = wm.read(hit, original, register=True)
                    if how == "again":
                        reading = wm.look_again(reading, original)
            except Exception as error:  # noqa: BLE001
                out.append(f"{how}: {type(error).__name__}: {error}")
                continue
            d = wm.decide([reading])
            acc = float(np.mean([int(b) for b in d.bits] == message[0].numpy()))
            pose = "" if how == "true" else f" pose {pose_error(original, camera, reading.found, h, w):.2f}px fov {reading.found.fov_y:.1f}"
            out.append(f"{how}: acc {acc:.3f} -log p {-math.log10(max(d.p_value, 1e-300)):.1f}{pose} "
                       f"({time.perf_counter() - started:.1f} s)")
        print(f"{index:3d} {dataset.rows[index]['id'][:36]:36s} | " + " | ".join(out), flush=True)


if __name__ == "__main__":
    main()
