"""The Mesh: positions, normals, uvs, faces and per-face materials, as torch tensors."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import torch

DEFAULT_AMBIENT = 0.25
DEFAULT_DIFFUSE = 1.0
DEFAULT_SPECULAR = 0.0
DEFAULT_SHININESS = 32.0


def _rgb(value: float) -> torch.Tensor:
    return torch.full((3,), float(value))


@dataclass
class Material:
    """The seed's material block (ambient, diffuse, specular RGB + shininess) and a texture image.

    `texture` is (H, W, 3) float in [0, 1] (row 0 = top) or None for a flat white albedo.
    """

    name: str = "default"
    texture: torch.Tensor | None = None
    ambient: torch.Tensor = field(default_factory=lambda: _rgb(DEFAULT_AMBIENT))
    diffuse: torch.Tensor = field(default_factory=lambda: _rgb(DEFAULT_DIFFUSE))
    specular: torch.Tensor = field(default_factory=lambda: _rgb(DEFAULT_SPECULAR))
    shininess: float = DEFAULT_SHININESS

    def to(self, device=None) -> "Material":
        texture = None if self.texture is None else self.texture.to(device)
        return replace(self, texture=texture, ambient=self.ambient.to(device),
                       diffuse=self.diffuse.to(device), specular=self.specular.to(device))


@dataclass
class Mesh:
    """A triangle mesh with all parts concatenated.

    positions, normals: (V, 3) float; uvs: (V, 2) float or None; faces: (F, 3) int64;
    face_material: (F,) int64 indexing `materials`. `up_axis` is the file's up axis ('y' or 'z').
    `source` keeps what saving needs to write the changes back into the original file's structure.
    """

    positions: torch.Tensor
    normals: torch.Tensor
    faces: torch.Tensor
    uvs: torch.Tensor | None = None
    face_material: torch.Tensor | None = None
    materials: list[Material] = field(default_factory=lambda: [Material()])
    up_axis: str = "z"
    source: Any = None

    def __post_init__(self):
        if self.face_material is None:
            self.face_material = torch.zeros(self.faces.shape[0], dtype=torch.long, device=self.faces.device)

    @property
    def n_vertices(self) -> int:
        return self.positions.shape[0]

    @property
    def n_faces(self) -> int:
        return self.faces.shape[0]

    @property
    def textures(self) -> list[torch.Tensor | None]:
        return [material.texture for material in self.materials]

    def to(self, device) -> "Mesh":
        return replace(self, positions=self.positions.to(device), normals=self.normals.to(device),
                       faces=self.faces.to(device), uvs=None if self.uvs is None else self.uvs.to(device),
                       face_material=self.face_material.to(device),
                       materials=[m.to(device) for m in self.materials])

    def copy(self) -> "Mesh":
        """A deep copy of the tensors (the `source` link is shared, it is read-only)."""
        return replace(self, positions=self.positions.clone(), normals=self.normals.clone(),
                       faces=self.faces.clone(), uvs=None if self.uvs is None else self.uvs.clone(),
                       face_material=self.face_material.clone(),
                       materials=[replace(m, texture=None if m.texture is None else m.texture.clone())
                                  for m in self.materials])
