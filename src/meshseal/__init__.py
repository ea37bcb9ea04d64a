"""meshseal: invisible watermarks in textured 3D meshes, read back from 2D renderings."""

from .errors import MeshError, MeshsealError
from .mesh import Mesh, Material, load as load_mesh, save as save_mesh
from .api import Detection, Watermarker, load, shipped_models

__version__ = "0.1.0"

__all__ = ["load", "Watermarker", "Detection", "shipped_models", "Mesh", "Material", "MeshError", "MeshsealError", "load_mesh", "save_mesh", "__version__"]
