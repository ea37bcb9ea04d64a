"""A folder of the user's own mesh files as an evaluation set: `meshseal eval --data FOLDER` measures
how the mark does on those assets (their own textures at their own sizes, not the dataset builder's
re-processed copies), with every attack `meshseal eval --attacks` runs on the test split.

Each file meshseal reads (`mesh_formats.SUPPORTED`, found recursively, in name order) becomes one item in
the dataset's form (`data.dataset.MeshDataset`: the tensors of one mesh in the canonical frame, z up,
its bounding box centred and its largest extent spanning [-1, 1]). Only what one texture covers can be such an item: a file without a
texture and UVs, or with several materials, is left out and said why (`skipped`).
"""

from __future__ import annotations

from pathlib import Path

import torch

from ..errors import MeshsealError


class AssetFolder(torch.utils.data.Dataset):
    """The textured single-material meshes under `root`, each an item as `MeshDataset` gives one.
    `skipped`: (path, why) of each mesh file left out."""

    def __init__(self, root: Path):
        from ..errors import MeshError
        from ..mesh import load, normalize, to_z_up
        from ..mesh_formats import SUPPORTED

        root = Path(root)
        if not root.is_dir():
            raise MeshsealError(f"{root}: not a folder")
        self.root, self.items, self.skipped = root, [], []
        for path in sorted(p for p in root.rglob("*") if p.is_file() and p.suffix.lower() in SUPPORTED):
            try:
                mesh = load(path)
            except MeshError as error:
                self.skipped.append((path, str(error)))
                continue
            textured = [m for m in mesh.materials if m.texture is not None]
            if mesh.uvs is None or not textured:
                self.skipped.append((path, "no texture and UVs to carry a mark"))
            elif len(mesh.materials) > 1:
                self.skipped.append((path, f"{len(mesh.materials)} materials (an item holds one texture)"))
            else:
                self.items.append(_item(normalize(to_z_up(mesh)), textured[0].texture, path.relative_to(root)))
        if not self.items:
            raise MeshsealError(f"{root}: no textured single-material mesh to evaluate (and no manifest of a "
                                f"meshseal dataset)")

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, index: int) -> dict:
        return dict(self.items[index])


def _item(mesh, texture: torch.Tensor, name: Path) -> dict:
    """One mesh in the canonical frame and its texture (H, W, 3) -> a dataset item."""
    return {"positions": mesh.positions.float().contiguous(), "normals": mesh.normals.float().contiguous(),
            "uvs": mesh.uvs.float().contiguous(), "faces": mesh.faces.long().contiguous(),
            "n_verts": torch.tensor(mesh.positions.shape[0], dtype=torch.long),
            "n_faces": torch.tensor(mesh.faces.shape[0], dtype=torch.long),
            "texture": texture.float().permute(2, 0, 1).contiguous(), "id": str(name)}
