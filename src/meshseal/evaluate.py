"""Evaluation on a data split: bit accuracy, rendered and texture PSNR/SSIM, vertex changes.

Deterministic for a seed: the same meshes, messages, cameras and lights every time.
"""

from __future__ import annotations

import torch

from .data.dataset import collate
from .distortions import Distortions2D, Distortions3D
from .losses import bit_accuracy, masked_l1, psnr, ssim
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
    accuracies, psnrs, ssims, texture_psnrs, normal_l1, uv_l1 = [], [], [], [], [], []
    device = next(model.parameters()).device
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
        "psnr_render": float(finite(torch.cat(psnrs)).mean()),
        "ssim_render": float(torch.cat(ssims).mean()),
        "psnr_texture": float(finite(torch.cat(texture_psnrs)).mean()),
        "l1_normal": float(torch.cat(normal_l1).mean()),
        "l1_uv": float(torch.cat(uv_l1).mean()),
        "n_meshes": count,
        "n_views": views,
    }
