"""Evaluation on a data split: bit accuracy, what a person sees (PSNR, SSIM and FLIP over the object's
pixels; whole-frame PSNR/SSIM as `psnr_render`/`ssim_render`, as the seed paper reports), texture
PSNR, vertex changes.

Deterministic for a seed: the same meshes, messages, cameras and lights every time.
"""

from __future__ import annotations

import time

import torch

from .data.dataset import collate
from .distortions import Distortions2D, Distortions3D
from .losses import bit_accuracy, masked_l1, psnr, ssim
from .metrics import visibility
from .models import WatermarkModel
from .pipeline import run_pass
from .render import MeshRenderer


@torch.no_grad()
def evaluate(model: WatermarkModel, dataset, n_meshes: int | None = None, views: int = 1, seed: int = 0,
             render_size: int = 128, sampler: str = "seed", batch_size: int = 8,
             distortions_3d: Distortions3D | None = None, distortions_2d: Distortions2D | None = None,
             unrender_jitter: float = 0.0) -> dict:
    was_training = model.training
    model.eval()
    generator = torch.Generator().manual_seed(seed + 1_000_003)
    renderer = MeshRenderer()
    count = len(dataset) if n_meshes is None else min(n_meshes, len(dataset))
    accuracies, psnrs, ssims, texture_psnrs, normal_l1, uv_l1, seen = [], [], [], [], [], [], []
    device = model.device
    for view in range(views):
        for start in range(0, count, batch_size):
            items = [dataset[i] for i in range(start, min(count, start + batch_size))]
            batch = collate(items, device)
            n = len(items)
            message = torch.randint(0, 2, (n, model.n_bits), generator=generator).float().to(device)
            out = run_pass(model, batch, message, renderer, generator, render_size, sampler,
                           distortions_3d, distortions_2d, unrender_jitter=unrender_jitter)
            mask = out.vertex_mask
            accuracies.append(bit_accuracy(out.logits, message))
            psnrs.append(psnr(out.render_marked, out.render))
            seen.append(visibility(out.render.cpu(), out.render_marked.cpu(), out.coverage.cpu()))
            ssims.append(ssim(out.render_marked, out.render))
            texture_psnrs.append(psnr(out.texture_marked, out.texture))
            normal_l1.append(masked_l1(out.normals_marked, out.normals, mask).reshape(1))
            uv_l1.append(masked_l1(out.uvs_marked, out.uvs, mask).reshape(1))
    model.train(was_training)
    accuracy = torch.cat(accuracies)
    finite = lambda values: values[torch.isfinite(values)]  # noqa: E731 (identical images: infinite PSNR)
    return {
        "bit_acc": float(accuracy.mean()),
        "bit_acc_std": float(accuracy.std()) if len(accuracy) > 1 else 0.0,
        "psnr_object": sum(s["psnr_object"] for s in seen) / len(seen),
        "ssim_object": sum(s["ssim_object"] for s in seen) / len(seen),
        "flip_object": sum(s["flip_object"] for s in seen) / len(seen),
        "psnr_render": float(finite(torch.cat(psnrs)).mean()),
        "ssim_render": float(torch.cat(ssims).mean()),
        "psnr_texture": float(finite(torch.cat(texture_psnrs)).mean()),
        "l1_normal": float(torch.cat(normal_l1).mean()),
        "l1_uv": float(torch.cat(uv_l1).mean()),
        "n_meshes": count,
        "n_views": views,
    }


def evaluate_registered(model: WatermarkModel, dataset, n_meshes: int | None = None, seed: int = 0,
                        size: int = 256, sampler: str = "seed", log=None) -> dict:
    """Informed models end to end, as `meshseal detect --register` runs: each test mesh is watermarked,
    rendered once (size x size, random view and light from `sampler`'s ranges, plain random
    background), the object is found in the picture, its camera registered against the original mesh,
    and the picture un-rendered and decoded. Slow (a registration per picture)."""
    from .framing import object_mask
    from .pipeline import random_backgrounds, read_bits, sample_views
    from .register import pose_error, register
    from .render import MeshBatch

    if not model.informed:
        raise ValueError("registration is for informed models")
    was_training = model.training
    model.eval()
    generator = torch.Generator().manual_seed(seed + 2_000_003)
    renderer = MeshRenderer()
    count = len(dataset) if n_meshes is None else min(n_meshes, len(dataset))
    accuracies, known, ious, errors, seconds = [], [], [], [], []
    device = model.device
    for index in range(count):
        batch = collate([dataset[index]], device)
        message = torch.randint(0, 2, (1, model.n_bits), generator=generator).float().to(device)
        positions, normals, uvs, faces, texture = (batch[k] for k in ("positions", "normals", "uvs", "faces", "texture"))
        with torch.no_grad():
            normals_marked, uvs_marked, texture_marked = model.embed(positions, normals, uvs, texture, message)
            cameras, lights = sample_views(1, sampler, generator)
            background = random_backgrounds(1, generator)
            picture = renderer(MeshBatch.from_tensors(positions, normals_marked, uvs_marked, faces, texture_marked),
                               cameras, lights, size, size, background).image[0].clamp(0, 1)
            picture = torch.round(picture * 255) / 255  # what a saved 8-bit PNG holds
        mask, found_background = object_mask(picture.permute(1, 2, 0).cpu().numpy())
        original = MeshBatch.from_tensors(positions, normals, uvs, faces, texture)
        started = time.perf_counter()
        found = register(original, picture, torch.from_numpy(mask), torch.from_numpy(found_background).to(picture))
        seconds.append(time.perf_counter() - started)
        with torch.no_grad():
            logits = read_bits(model, original, picture[None], found.camera)
            known.append(bit_accuracy(read_bits(model, original, picture[None], cameras), message))
        accuracies.append(bit_accuracy(logits, message))
        ious.append(found.iou)
        errors.append(pose_error(original, cameras, found.camera, size, size))
        if log is not None:
            log(f"mesh {index + 1}/{count}: bit_acc {float(accuracies[-1]):.4f} (known camera {float(known[-1]):.4f}) "
                f"pose error {errors[-1]:.2f} px, IoU {found.iou:.3f}, {seconds[-1]:.1f} s")
    model.train(was_training)
    accuracy, pose = torch.cat(accuracies), torch.tensor(errors)
    success = (pose < 0.5) | (torch.tensor(ious) >= 0.95)
    return {"bit_acc": float(accuracy.mean()), "bit_acc_std": float(accuracy.std()) if count > 1 else 0.0,
            "bit_acc_known_camera": float(torch.cat(known).mean()),
            "registration_success": float(success.float().mean()), "registration_iou": float(sum(ious) / len(ious)),
            "pose_error_px": {q: round(float(pose.nanquantile(v)), 3) for q, v in (("median", 0.5), ("p90", 0.9),
                                                                                 ("max", 1.0))},
            "seconds_per_picture": sum(seconds) / len(seconds), "n_meshes": count, "n_views": 1, "size": size}
