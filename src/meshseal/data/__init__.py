"""Training and test data: build a dataset from real 3D assets (`meshseal data build`) and serve it."""

from .build import build, dataset_stats, read_manifest
from .dataset import MeshDataset
from .sources import DataError

__all__ = ["build", "dataset_stats", "read_manifest", "MeshDataset", "DataError"]
