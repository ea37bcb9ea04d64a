"""A torch Dataset over a built meshseal dataset folder (see `meshseal.data.build`)."""

from __future__ import annotations

import json
import zlib
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from .build import read_manifest
from .process import noise_texture, random_crop
from .sources import DataError

SPLITS = ("train", "test", "test_cc0", "all")


class MeshDataset(torch.utils.data.Dataset):
    """Fixed-size items for training and evaluation.

    Each item is a dict: positions (Vmax, 3), normals (Vmax, 3), uvs (Vmax, 2) float32; faces (Fmax, 3)
    int64 (padding faces are [0, 0, 0]); texture (3, T, T) float in [0, 1]; n_verts, n_faces (int64
    scalars); id (str). Batches stack with the default collate.

    retexture: probability (0..1, or True = 1) that an item gets a fresh texture instead of its stored
    one: a random crop of a random pool image or Gaussian-smoothed noise (`p_noise`), drawn from
    (seed, epoch, index) so that every epoch differs and runs repeat. Call `set_epoch` each epoch.
    """

    def __init__(self, root, split: str = "train", retexture: float | bool = 0.0, p_noise: float = 0.5,
                 seed: int = 0, categories=None, texture_kinds=None):
        self.root = Path(root)
        if split not in SPLITS:
            raise DataError(f"unknown split '{split}' (one of {', '.join(SPLITS)})")
        rows = read_manifest(self.root)
        if split == "test_cc0":
            rows = [r for r in rows if r.get("publishable")]
        elif split != "all":
            rows = [r for r in rows if r["split"] == split]
        if categories:
            rows = [r for r in rows if r["category"] in set(categories)]
        if texture_kinds:  # e.g. ("noise", "real"): the items with spherical UVs, as in the seed's ModelNet
            rows = [r for r in rows if r.get("texture_kind") in set(texture_kinds)]
        self.rows = rows
        self.retexture = float(retexture)
        self.p_noise = float(p_noise)
        self.seed = int(seed)
        self.epoch = 0
        pool_file = self.root / "textures" / "pool.jsonl"
        self.pool = [self.root / json.loads(line)["file"] for line in pool_file.read_text().splitlines()
                     if line.strip()] if pool_file.is_file() else []
        config_file = self.root / "build_config.json"
        config = json.loads(config_file.read_text()) if config_file.is_file() else {}
        self.texture_size = int(config.get("texture_size", 128))

    def __len__(self) -> int:
        return len(self.rows)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def _rng(self, index: int) -> np.random.Generator:
        key = zlib.crc32(self.rows[index]["id"].encode())
        return np.random.default_rng(np.random.SeedSequence([self.seed, self.epoch, key]))

    def texture_for(self, index: int) -> np.ndarray:
        row = self.rows[index]
        if self.retexture > 0.0:
            rng = self._rng(index)
            if rng.random() < self.retexture:
                if self.pool and rng.random() >= self.p_noise:
                    image = np.asarray(Image.open(self.pool[int(rng.integers(len(self.pool)))]).convert("RGB"))
                    return random_crop(image, rng, self.texture_size)
                return noise_texture(rng, self.texture_size)
        return np.asarray(Image.open(self.root / row["texture_file"]).convert("RGB"))

    def __getitem__(self, index: int) -> dict:
        row = self.rows[index]
        with np.load(self.root / row["file"]) as data:
            item = {
                "positions": torch.from_numpy(data["positions"].astype(np.float32)),
                "normals": torch.from_numpy(data["normals"].astype(np.float32)),
                "uvs": torch.from_numpy(data["uvs"].astype(np.float32)),
                "faces": torch.from_numpy(data["faces"].astype(np.int64)),
                "n_verts": torch.tensor(int(data["n_verts"]), dtype=torch.long),
                "n_faces": torch.tensor(int(data["n_faces"]), dtype=torch.long),
            }
        texture = self.texture_for(index)
        item["texture"] = torch.from_numpy(np.array(texture, dtype=np.uint8)).permute(2, 0, 1).float() / 255.0
        item["id"] = row["id"]
        return item


def collate(items: list[dict], device=None) -> dict:
    """Stack the tensor fields of dataset items into a batch (string fields such as `id` are dropped)."""
    return {key: torch.stack([item[key] for item in items]).to(device)
            for key in items[0] if torch.is_tensor(items[0][key])}


def vertex_mask(batch: dict) -> torch.Tensor:
    """(B, Vmax) 1 for a mesh's real vertices, 0 for the padding."""
    positions = batch["positions"]
    return (torch.arange(positions.shape[1], device=positions.device)[None] < batch["n_verts"][:, None]).float()
