"""Training and test data: build a dataset from real 3D assets (`meshseal data build`) and serve it.

The names below are imported on first use (`meshseal._lazy`): the command line registers `meshseal data`
without importing torch.
"""

from .._lazy import export_lazily

__all__ = ["build", "dataset_stats", "read_manifest", "MeshDataset", "DataError"]

export_lazily(__name__, {"build": ".build", "dataset_stats": ".build", "read_manifest": ".build",
                         "MeshDataset": ".dataset", "DataError": ".sources"})
