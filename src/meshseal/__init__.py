"""meshseal: invisible watermarks in textured 3D meshes, read back from 2D renderings.

The public names are imported on first use (`meshseal._lazy`), so that `import meshseal` and the command
line's `--help` and argument errors do not import torch, numba or trimesh.
"""

from ._lazy import export_lazily
from .errors import MeshError, MeshsealError

__version__ = "0.1.0"

__all__ = ["load", "Watermarker", "Detection", "shipped_models", "Mesh", "Material", "MeshError", "MeshsealError", "load_mesh", "save_mesh", "__version__"]

export_lazily(__name__, {"Mesh": ".mesh", "Material": ".mesh", "load_mesh": ".mesh:load", "save_mesh": ".mesh:save",
                         "Detection": ".api", "Watermarker": ".api", "load": ".api", "shipped_models": ".api"})
