"""Meshes: the `Mesh` type, file I/O through trimesh, and preprocessing."""

from ..errors import MeshError
from .core import Material, Mesh
from .io import load, save
from .preprocess import Y_UP_TO_Z_UP, decimate, normalize, simplify, spherical_uv, to_z_up, vertex_normals

__all__ = ["Mesh", "Material", "MeshError", "load", "save", "decimate", "normalize", "simplify", "spherical_uv",
           "to_z_up", "vertex_normals", "Y_UP_TO_Z_UP"]
