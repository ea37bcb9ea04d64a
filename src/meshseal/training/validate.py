"""The training pass measured on a data split (validation, `meshseal eval` without --register): bit
accuracy, what a person sees (PSNR, SSIM and FLIP over the object's pixels; whole-frame PSNR/SSIM as
`psnr_render`/`ssim_render`, as the seed paper reports), texture PSNR, vertex changes.

Deterministic for a seed: the same meshes, messages, cameras and lights every time.
"""

from __future__ import annotations


import torch

from ..data.dataset import collate
from ..evaluation.metrics import shown_texture_psnr, visibility
from ..methods.batches import batch_texels_used
from ..models import WatermarkModel
from ..render import MeshRenderer
from .distortions import Distortions2D, Distortions3D
from .losses import bit_accuracy, masked_l1, psnr, ssim
from .step import run_pass


@torch.no_grad()
def evaluate(model: WatermarkModel, dataset, n_meshes: int | None = None, views: int = 1, seed: int = 0,
             render_size: int = 128, sampler: str = "seed", batch_size: int = 8,
             distortions_3d: Distortions3D | None = None, distortions_2d: Distortions2D | None = None,
             unrender_jitter: float = 0.0, progress: bool = False) -> dict:
    """Bit accuracy and what the mark changed over `n_meshes` of `dataset` x `views` (see `meshseal
    eval`); `progress`: a bar of the meshes read on stderr."""
    import sys

    from tqdm import tqdm

    was_training = model.training
    model.eval()
    generator = torch.Generator().manual_seed(seed + 1_000_003)
    renderer = MeshRenderer()
    count = len(dataset) if n_meshes is None else min(n_meshes, len(dataset))
    accuracies, psnrs, ssims, texture_psnrs, normal_l1, uv_l1, seen = [], [], [], [], [], [], []
    render_l1, texture_l1, texture_ssims, shown_psnrs = [], [], [], []
    device = model.device
    bar = tqdm(total=views * count, unit="mesh", file=sys.stderr, disable=not progress)
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
            shown = out.shown if out.shown is not None else batch_texels_used(batch)  # learned marks: worked out here
            shown_psnrs.append(shown_texture_psnr(out.texture_marked, out.texture, shown))
            render_l1.append((out.render_marked - out.render).abs().mean().reshape(1))
            texture_l1.append((out.texture_marked - out.texture).abs().mean().reshape(1))
            texture_ssims.append(ssim(out.texture_marked, out.texture))
            normal_l1.append(masked_l1(out.normals_marked, out.normals, mask).reshape(1))
            uv_l1.append(masked_l1(out.uvs_marked, out.uvs, mask).reshape(1))
            bar.update(n)
    bar.close()
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
        "psnr_texture_shown": float(finite(torch.cat(shown_psnrs)).mean()),
        "ssim_texture": float(torch.cat(texture_ssims).mean()),
        "l1_texture": float(torch.cat(texture_l1).mean()),
        "l1_render": float(torch.cat(render_l1).mean()),
        "l1_normal": float(torch.cat(normal_l1).mean()),
        "l1_uv": float(torch.cat(uv_l1).mean()),
        "n_meshes": count,
        "n_views": views,
    }
