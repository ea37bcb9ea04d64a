"""What `meshseal embed` reports about a marked mesh (texture PSNR, normal and uv change, visibility in
renders) and the preview sheet a person judges it by."""

from __future__ import annotations

import math
from pathlib import Path


def embed_report(original, marked, views: int) -> tuple[dict, tuple]:
    """How much the mark changed the mesh: texture PSNR, normal angle, uv shift, and what a person sees
    in renders (256^2, seed views): PSNR, SSIM and FLIP over the object's pixels, PSNR/SSIM over the
    whole frame beside them (as the seed paper reports; the background inflates them). Also returns
    the renders (original, marked) for a preview."""
    import torch

    from ..training.losses import normal_angle_deg, psnr, ssim
    from .metrics import render_pair, shown_texture_psnr, visibility
    from ..models.spread import resampled_like, texels_used

    texture_psnr, shown_psnr, shifts = [], [], []
    for index, (before, after) in enumerate(zip(original.materials, marked.materials)):
        if before.texture is not None and after.texture is not None:
            after_texture, before_texture = after.texture.permute(2, 0, 1)[None], before.texture.permute(2, 0, 1)[None]
            texture_psnr.append(float(psnr(after_texture, resampled_like(before_texture, after_texture))))
            shown = texels_used(original.uvs, original.faces[original.face_material == index], *before_texture.shape[-2:]) \
                if original.uvs is not None else None
            if shown is not None and bool(shown.any()):
                shown_psnr.append(float(shown_texture_psnr(after_texture, before_texture, shown[None, None])[0]))
    if original.uvs is not None and marked.uvs is not None:
        sizes = torch.tensor([max(m.texture.shape[:2]) if m.texture is not None else 0 for m in original.materials],
                             dtype=torch.float32)
        per_vertex = torch.zeros(original.n_vertices)
        per_vertex[original.faces.reshape(-1)] = sizes[original.face_material].repeat_interleave(3)
        shifts.append(float(((marked.uvs - original.uvs).norm(dim=-1) * per_vertex).mean()))
    report = {
        "psnr_texture": round(sum(texture_psnr) / len(texture_psnr), 3) if texture_psnr else None,
        "psnr_texture_shown": round(sum(shown_psnr) / len(shown_psnr), 3) if shown_psnr else None,
        "normal_angle_deg": round(float(normal_angle_deg(marked.normals, original.normals)), 4),
        "uv_shift_texels": round(shifts[0], 4) if shifts else 0.0,
        "views": views,
    }
    if views == 0:  # no renders: the file figures only
        return report, None
    render_a, render_b, inside = render_pair(original, marked, views)
    seen = visibility(render_a, render_b, inside)
    measured = lambda value, digits: None if math.isnan(value) else round(value, digits)  # noqa: E731 (NaN: not seen)
    report |= {
        "psnr_object": measured(seen["psnr_object"], 3),
        "ssim_object": measured(seen["ssim_object"], 5),
        "flip_object": measured(seen["flip_object"], 4),
        "psnr_frame": round(float(psnr(render_b, render_a).mean()), 3),
        "ssim_frame": round(float(ssim(render_b, render_a).mean()), 5),
    }
    return report, (render_a[0], render_b[0])


def write_preview(path: Path, original, marked, renders) -> None:
    """A sheet a person can judge, written atomically as PNG: columns original | marked | difference x4
    (grey is no change), labelled; one row per textured material (its name and size above it) and one
    render."""
    import torch
    from PIL import Image, ImageDraw, ImageFont

    from ..mesh.files import atomic_write
    from ..reading.pictures import image_bytes
    from ..models.spread import resampled_like

    width, band, gap = 256, 18, 6
    rows = [(f"texture '{b.name}' ({b.texture.shape[1]}x{b.texture.shape[0]})",
             resampled_like(a.texture.permute(2, 0, 1), b.texture.permute(2, 0, 1)), b.texture.permute(2, 0, 1))
            for a, b in zip(original.materials, marked.materials) if a.texture is not None and b.texture is not None]
    rows.append(("render (256x256)", *renders))
    tiles = []
    for _, before, after in rows:
        rows_of, cols_of = before.shape[-2:]  # fitted into the square, its aspect kept (a charted texture is tall)
        fit = width / max(rows_of, cols_of)
        size = (max(1, round(rows_of * fit)), max(1, round(cols_of * fit)))
        before, after = (torch.nn.functional.interpolate(x[None].float(), size=size, mode="area")[0]
                         for x in (before, after))
        row = [before, after, (0.5 + 4.0 * (after - before)).clamp(0, 1)]
        row = torch.cat([torch.nn.functional.pad(tile, (0, width - size[1], 0, width - size[0]), value=0.5)
                         for tile in row], dim=2)
        tiles.append((row.clamp(0, 1) * 255).round().byte().permute(1, 2, 0).numpy())
    sheet = Image.new("RGB", (3 * width + 2 * gap, band + len(rows) * (band + width)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    font = ImageFont.load_default(size=13)
    for column, label in enumerate(("original", "marked", "difference x4")):
        draw.text((column * (width + gap) + 4, 2), label, fill=(0, 0, 0), font=font)
    for index, ((label, _, _), tile) in enumerate(zip(rows, tiles)):
        top = band + index * (band + width)
        draw.text((4, top + 2), label, fill=(60, 60, 60), font=font)
        for column in range(3):
            sheet.paste(Image.fromarray(tile[:, column * width:(column + 1) * width]), (column * (width + gap), top + band))
    atomic_write(path, image_bytes(sheet))
