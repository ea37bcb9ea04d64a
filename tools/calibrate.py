"""Check the detection decision of a calibrated model on real pictures, and measure its true positives.

False positives: every test mesh, *unmarked*, rendered from many seeded views at `--null-size`^2
(half the paper's range, half all around; random light and background; 8-bit values), each picture
also re-saved as JPEG (quality 75) and resized to twice its size. Each is read under the public key with its own camera (from
metadata, as `meshseal render` writes it). Under the null model (no mark under this key) the p-values
are uniform: the histogram, a KS test against the uniform distribution and the count at or below the
threshold `payload.FPR` say whether they are.

True positives: every test mesh marked with a random 32-bit asset ID (strength 1, public key), one
seed-range `--size`^2 picture each, read with the camera known (as is, and after JPEG 75, half size,
noise, blur), and for the first `--registered` meshes three pictures each, read with the camera registered
(no metadata) one by one and pooled. Reports the detection rate at FPR 1e-6 (TPR) and the exact-
message rate.

    python tools/calibrate.py --data data --out docs [--views 36] [--null-size 128] [--registered 100]

Writes OUT/calibration.md, OUT/calibration_pvalues.png and OUT/calibration.json (with `--views 0`, no
clean pictures: OUT/calibration_registered.md and .json).
"""

from __future__ import annotations

import argparse
import io
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from scipy import stats

import meshseal
from meshseal import payload
from meshseal.reading.read import Reading
from meshseal.data.dataset import MeshDataset, collate
from meshseal.imaging import gaussian_blur
from meshseal.methods.batches import batch_mark_grid, batch_texels_used, charted_item
from meshseal.training.views import random_backgrounds
from meshseal.render.views import sample_views
from meshseal.methods.spread import spread_evidence
from meshseal.render import MeshBatch, MeshRenderer


def quantise(images: torch.Tensor) -> torch.Tensor:
    return torch.round(images.clamp(0, 1) * 255) / 255


def jpeg(images: torch.Tensor, quality: int = 75) -> torch.Tensor:
    """Each picture (B, 3, H, W) through a JPEG file of `quality` and back."""
    out = []
    for image in images:
        buffer = io.BytesIO()
        Image.fromarray((image.permute(1, 2, 0).cpu().numpy() * 255).round().astype(np.uint8)).save(
            buffer, format="JPEG", quality=quality)
        decoded = np.asarray(Image.open(io.BytesIO(buffer.getvalue())).convert("RGB"), dtype=np.float32) / 255
        out.append(torch.from_numpy(decoded).permute(2, 0, 1))
    return torch.stack(out).to(images)


def variants(pictures: torch.Tensor, generator: torch.Generator, attacks: bool, scale: float = 0.5) -> dict[str, torch.Tensor]:
    """The pictures as saved, re-saved as JPEG 75 and resized by `scale`; with `attacks` also noise and blur."""
    out = {"png": pictures, "jpeg75": jpeg(pictures),
           f"resized_x{scale:g}": quantise(F.interpolate(pictures, scale_factor=scale, mode="bilinear", antialias=True))}
    if attacks:
        noise = torch.randn(pictures.shape, generator=generator).to(pictures) * (2.0 / 255)
        out["noise_2"] = quantise(pictures + noise)
        out["blur_0.7"] = quantise(gaussian_blur(pictures, 0.7))
    return out


def mesh_batches(dataset: MeshDataset, index: int, device) -> tuple[MeshBatch, dict]:
    """Test mesh `index` as the original detection prepares and the batch embedding marks (palette faces
    charted, as `Watermarker.layout` charts them)."""
    batch = charted_item(collate([dataset[index]], device))
    original = MeshBatch.from_tensors(*(batch[k] for k in ("positions", "normals", "uvs", "faces", "texture")))
    return original, batch


def pvalues(wm, evidence: torch.Tensor, tries: int = 1) -> tuple[torch.Tensor, float, float]:
    """Soft bits of one picture's (or a pool's) cell sums (1, C) and its detection p-value as
    `Watermarker.decide` gives it (the likeliest of the grids read; Bonferroni over them and over the
    `tries` a second look made) under the exact null, and under the N(0, 1) null for comparison."""
    soft, weights, grids = wm.method.soft_bits(evidence, None, None)
    return (soft, min(1.0, grids * tries * float(payload.detection_pvalue(soft, weights))),
            min(1.0, grids * tries * float(payload.detection_pvalue(soft))))


def null_pvalues(wm, dataset, views: int, size: int, seed: int, device, log) -> dict[str, np.ndarray]:
    """Clean pictures' p-values under the exact null (`payload.detection_pvalue` with the picture's
    cell weights), and for comparison under the N(0, 1) model (names ending ', N(0, 1) null')."""
    model = wm.model
    renderer, generator = MeshRenderer(), torch.Generator().manual_seed(seed)
    results: dict[str, list] = {}
    for index in range(len(dataset)):
        original, _ = mesh_batches(dataset, index, device)
        for sampler, count in (("seed", views // 2), ("any", views - views // 2)):
            cameras, lights = sample_views(count, sampler, generator)
            cameras, lights = cameras.to(device), lights.to(device)
            with torch.no_grad():
                pictures = quantise(renderer(original, cameras, lights, size, size,
                                             random_backgrounds(count, generator).to(device)).image)
                for name, images in variants(pictures, generator, attacks=False, scale=2.0).items():
                    evidence = spread_evidence(model, original, images, cameras, grids=wm.method.grids_to_read(original))
                    for row in evidence.cpu():
                        _, exact, gaussian = pvalues(wm, row[None])
                        results.setdefault(name, []).append(exact)
                        results.setdefault(f"{name}, N(0, 1) null", []).append(gaussian)
        if log and (index + 1) % 20 == 0:
            log(f"null: {index + 1}/{len(dataset)} meshes, {sum(len(v) for v in results.values())} pictures")
    return {name: np.array(values) for name, values in results.items()}


def true_positives(wm, dataset, size: int, registered: int, seed: int, device, log) -> dict[str, dict]:
    model, key_seed = wm.model, payload.key_seed(None)
    renderer, generator = MeshRenderer(), torch.Generator().manual_seed(seed + 1)
    counts: dict[str, list] = {}
    registration_seconds = []

    def record(name: str, readings: list, asset: int) -> None:
        """The decision on `readings` (`Watermarker.read`'s: one picture, or several pooled; none:
        refused) as `meshseal detect` makes it, whether its message is the asset's, and the decision
        under the N(0, 1) null for comparison."""
        if not readings:
            counts.setdefault(name, []).append((False, False, False))
            return
        soft, exact, gaussian = pvalues(wm, torch.stack([r.evidence for r in readings]).sum(0, keepdim=True),
                                        math.prod(r.tries for r in readings))
        counts.setdefault(name, []).append((payload.detected(exact), payload.decode(soft).message == asset,
                                            payload.detected(gaussian)))

    def known(evidence: torch.Tensor) -> list:
        """Cell sums (1, C) read with the camera known, as a reading."""
        return [Reading(evidence[0].cpu(), (0.0, 0.0, 0.0), "given", None)]

    for index in range(len(dataset)):
        original, batch = mesh_batches(dataset, index, device)
        asset = int(torch.randint(0, 2 ** 32, (1,), generator=generator))
        raw = payload.encode(payload.Message.id(asset), None, wm.n_bits).to(device)[None]
        with torch.no_grad():  # marked as `meshseal embed` marks it: the mesh's cell grid, on the texels it shows
            texture = model.texture_encoder(batch["texture"], raw, 1.0, key_seed, batch_mark_grid(model.texture_encoder, batch),
                                         batch_texels_used(batch))
        marked = MeshBatch.from_tensors(*(batch[k] for k in ("positions", "normals", "uvs", "faces")), texture)
        views = 3 if index < registered else 1
        cameras, lights = sample_views(views, "seed", generator)
        cameras, lights = cameras.to(device), lights.to(device)
        with torch.no_grad():
            pictures = quantise(renderer(marked, cameras, lights, size, size,
                                         random_backgrounds(views, generator).to(device)).image)
            for name, images in variants(pictures[:1], generator, attacks=True).items():
                record(f"known camera, {name}", known(spread_evidence(model, original, images, cameras[[0]],
                                                                      grids=wm.method.grids_to_read(original))), asset)
        if index >= registered:
            continue
        pooled = []
        for view in range(views):  # as `meshseal detect --mesh` reads a picture without metadata
            pixels = pictures[view].permute(1, 2, 0).cpu().numpy()
            started = time.perf_counter()
            try:
                reading = wm.read(pixels, original, register=True)
            except meshseal.MeshsealError:  # refused (no object found): counts as not detected
                reading = None
            registration_seconds.append(time.perf_counter() - started)
            if view == 0:
                record("registered, one picture", [wm.look_again(reading, original)] if reading else [], asset)
            if reading:
                pooled.append(wm.look_again(reading, original, search=False))  # pooled: no second look, as the CLI
        record("registered, 3 pictures pooled", pooled, asset)
        if log and (index + 1) % 10 == 0:
            log(f"marked: {index + 1}/{len(dataset)} meshes")
    table = {name: {"tpr": float(np.mean([d for d, _, _ in rows])), "exact_message": float(np.mean([e for _, e, _ in rows])),
                    "tpr_gaussian_null": float(np.mean([g for _, _, g in rows])), "pictures": len(rows)}
             for name, rows in counts.items()}
    if registration_seconds:
        table["registered, one picture"]["seconds_per_registration"] = float(np.mean(registration_seconds))
    return table


def write_report(out: Path, null: dict[str, np.ndarray], positives: dict, command: str, seconds: float,
                 name: str) -> dict:
    """OUT/NAME.md and OUT/NAME.json (and, with clean pictures, OUT/NAME_pvalues.png)."""
    out.mkdir(parents=True, exist_ok=True)
    summary = {"fpr_threshold": payload.FPR, "true_positives": positives, "seconds": round(seconds, 1)}
    lines = [f"# Detection decision: {'calibration and ' if null else ''}true positives", "",
             f"Made by `{command}` ({seconds / 60:.1f} min on this repository's 2-core CPU machine). Model `default`, "
             f"public key, threshold p <= {payload.FPR:g}.", ""]
    if null:
        summary["null"] = _null_section(out, null, name, lines)
    lines += ["## Marked pictures: true positives at FPR 1e-6", "",
              "| pictures | count | TPR | exact message | TPR under the N(0, 1) null |", "|---|---|---|---|---|"]
    for label, row in positives.items():
        lines.append(f"| {label} | {row['pictures']} | {row['tpr']:.4f} | {row['exact_message']:.4f} | "
                     f"{row['tpr_gaussian_null']:.4f} |")
    (out / f"{name}.md").write_text("\n".join(lines) + "\n")
    (out / f"{name}.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def _null_section(out: Path, null: dict[str, np.ndarray], name: str, lines: list[str]) -> dict:
    """The clean pictures' p-values: table rows into `lines`, histograms into OUT/NAME_pvalues.png."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    exact = {label: p for label, p in null.items() if not label.endswith("null")}
    gaussian = {label: p for label, p in null.items() if label.endswith("null")}
    rows = (list(exact.items()) + [("all", np.concatenate(list(exact.values())))] + list(gaussian.items())
            + [("all, N(0, 1) null", np.concatenate(list(gaussian.values())))])
    summary = {label: {"pictures": int(len(p)), "at_or_below_fpr": int((p <= payload.FPR).sum()),
                       "min_p": float(p.min()), "ks_uniform_p": float(stats.kstest(p, "uniform").pvalue)}
               for label, p in rows}
    figure, axes = plt.subplots(2, len(exact), figsize=(4 * len(exact), 6.2), squeeze=False)
    for row, (title, group) in enumerate((("exact null", exact), ("N(0, 1) null", gaussian))):
        for axis, (label, p) in zip(axes[row], group.items()):
            axis.hist(p, bins=20, range=(0, 1), color="#4c72b0" if row == 0 else "#999999")
            axis.axhline(len(p) / 20, color="k", lw=0.8, ls="--")
            axis.set_title(f"{label.split(',')[0]}, {title}: {len(p)} clean", fontsize=9)
            axis.set_xlabel("p-value")
    figure.tight_layout()
    figure.savefig(out / f"{name}_pvalues.png", dpi=110)
    lines += ["## Clean pictures (no mark): false positives", "",
              "p-values under the exact null (given each picture's cell evidence, the key's cell signs are fair "
              "coins: `payload.detection_pvalue` with `models.spread.bit_weights`), and below them, for comparison, "
              "under the N(0, 1) model (chi-square), which over-states them.", "",
              "| pictures | count | at or below the threshold | smallest p | KS test vs uniform (p) |", "|---|---|---|---|---|"]
    for label, row in summary.items():
        lines.append(f"| {label} | {row['pictures']} | {row['at_or_below_fpr']} | {row['min_p']:.3g} | "
                     f"{row['ks_uniform_p']:.3f} |")
    lines += ["", f"![p-value histograms]({name}_pvalues.png)", ""]
    return summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--out", type=Path, default=Path("docs"))
    parser.add_argument("--views", type=int, default=36, help="clean pictures per test mesh (default 36; 0: none)")
    parser.add_argument("--meshes", type=int, default=None, help="at most this many test meshes (default all)")
    parser.add_argument("--registered", type=int, default=100, help="meshes read through registration (default 100)")
    parser.add_argument("--size", type=int, default=256, help="marked pictures' size (default 256)")
    parser.add_argument("--null-size", type=int, default=128, help="clean pictures' size (default 128)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--model", default="default", help="shipped model name or .safetensors path")
    args = parser.parse_args()
    started = time.perf_counter()
    wm = meshseal.load(args.model, device=args.device)
    dataset = MeshDataset(args.data, "test")
    if args.meshes is not None:
        dataset.rows = dataset.rows[:args.meshes]
    null = null_pvalues(wm, dataset, args.views, args.null_size, args.seed, args.device, print) if args.views else {}
    positives = true_positives(wm, dataset, args.size, args.registered, args.seed, args.device, print)
    command = (f"python tools/calibrate.py --data DATA --out {args.out} --views {args.views} --null-size {args.null_size} "
               f"--size {args.size} --registered {args.registered}" + (f" --meshes {args.meshes}" if args.meshes else ""))
    summary = write_report(args.out, null, positives, command, time.perf_counter() - started,
                           "calibration" if null else "calibration_registered")
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
