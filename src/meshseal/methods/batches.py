"""Dataset batches as the methods mark them: one item without its padding, palette faces charted,
the texels each item shows (spread marks) or each texel's surface column (surface marks)."""

from __future__ import annotations

import torch

from ..models.spread import cell_pixels, texels_used
from ..models.surface import texel_columns


def unpadded(batch: dict, index: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Item `index` of a dataset batch without its padding: positions, normals, uvs (V, .), faces (F, 3)."""
    n_verts, n_faces = int(batch["n_verts"][index]), int(batch["n_faces"][index])
    return (batch["positions"][index, :n_verts], batch["normals"][index, :n_verts], batch["uvs"][index, :n_verts],
            batch["faces"][index, :n_faces])


def charted_item(batch: dict, index: int = 0) -> dict:
    """Item `index` of a dataset batch as a one-item batch (no padding) with its palette faces
    charted as `SpreadMethod.layout` charts a mesh for a spread mark (`methods.charts`); the item as it
    is (unpadded) where nothing is charted."""
    from ..mesh import Material, Mesh
    from .charts import chart_palette_faces

    positions, normals, uvs, faces = unpadded(batch, index)
    texture = batch["texture"][index]
    mesh = Mesh(positions.cpu(), normals.cpu(), faces.cpu(), uvs.cpu(),
                materials=[Material(texture=texture.permute(1, 2, 0).cpu())])
    charted = chart_palette_faces(mesh)
    device = texture.device
    return {"positions": charted.positions[None].to(device), "normals": charted.normals[None].to(device),
            "uvs": charted.uvs[None].to(device), "faces": charted.faces[None].to(device),
            "texture": charted.materials[0].texture.permute(2, 0, 1)[None].contiguous().to(device),
            "n_verts": torch.tensor([charted.n_vertices], device=device),
            "n_faces": torch.tensor([charted.n_faces], device=device)}


def batch_mark_grid(encoder, batch: dict, index: int = 0) -> int:
    """The cell grid a spread mark (`encoder`: a SpreadSpectrumEncoder) uses on item `index` of a
    dataset batch (its padding left out), as `Watermarker.embed` picks it for that mesh."""
    positions, _, uvs, faces = unpadded(batch, index)
    return encoder.grid_for(positions, faces, uvs)


def batch_cell_width(encoder, batch: dict, index: int = 0) -> float:
    """How wide a cell of a spread mark's own grid (`encoder`) is in a standard view
    (`models.spread.cell_pixels`) on item `index` of a dataset batch (its padding left out)."""
    positions, _, uvs, faces = unpadded(batch, index)
    return cell_pixels(positions, faces, uvs, encoder.chips)


def batch_texels_used(batch: dict) -> torch.Tensor:
    """The texels (B, 1, H, W) each mesh of a dataset batch shows (its padding left out), where a
    spread mark lies, as `Watermarker.embed` finds them (`models.spread.texels_used`)."""
    height, width = batch["texture"].shape[-2:]
    items = (unpadded(batch, index) for index in range(len(batch["texture"])))
    return torch.stack([texels_used(uvs, faces, height, width)
                        for _, _, uvs, faces in items])[:, None].to(batch["texture"].device)


def batch_texel_columns(batch: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """Each texel's column and whether it paints any (B, H, W) each, for every mesh of a dataset batch
    (its padding left out), where a surface mark lies (`models.surface.texel_columns`)."""
    height, width = batch["texture"].shape[-2:]
    pairs = [texel_columns(positions, normals, faces, uvs, height, width)
             for positions, normals, uvs, faces in (unpadded(batch, i) for i in range(len(batch["texture"])))]
    device = batch["texture"].device
    return torch.stack([c for c, _ in pairs]).to(device), torch.stack([p for _, p in pairs]).to(device)
