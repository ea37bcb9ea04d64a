"""Training and test data: build a dataset from real 3D assets (`meshseal data build`) and serve it.

The names below load on first use, so that commands that never touch a dataset (embed, detect) do not
pay for the builder's imports at start-up."""

from importlib import import_module

_NAMES = {"build": ".build", "dataset_stats": ".build", "read_manifest": ".build", "MeshDataset": ".dataset",
          "DataError": ".sources"}

__all__ = list(_NAMES)


def __getattr__(name: str):
    if name not in _NAMES:
        raise AttributeError(f"module 'meshseal.data' has no attribute '{name}'")
    return getattr(import_module(_NAMES[name], __name__), name)
