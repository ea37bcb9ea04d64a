"""Blender as a rendering backend: Cycles, Eevee and Workbench through `bpy` (the optional extra
`pip install -e '.[blender]'`), headless, behind the `Renderer` protocol.

The scene is what our renderer draws, translated to Blender's terms (docs/conventions.md): the mesh with
its UVs, vertex normals (custom split normals) and one Principled BSDF per material with the texture as
an sRGB image (bilinear, REPEAT); our cameras as Blender cameras (same view matrix, vertical field of
view, principal point as lens shift); our point light as a point, sun or area light of matching
brightness, or no lamp and only world light from one of Blender's bundled studio HDRIs. Blender shades
in linear light and applies a view transform (Standard or AgX), so its pictures differ from ours in
tone and soft shadows as a user's would: that difference is what detection has to survive.

All views of one call render in one Blender process (`blender_worker`): its start-up is paid once a call,
not once a view.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import MeshsealError
from ..mesh.core import Mesh
from . import LIGHT_KINDS, VIEW_TRANSFORMS
from .cameras import Cameras
from .lighting import ATTENUATION, K_AMBIENT, K_DIFFUSE, PointLights

ENGINES = ("cycles", "eevee", "workbench")
DEFAULT_SAMPLES = {"cycles": 64, "eevee": 16, "workbench": 8}
WORKER_TIMEOUT_S = 3600


def available() -> bool:
    """Whether `bpy` can be imported (the optional 'blender' extra is installed)."""
    import importlib.util

    return importlib.util.find_spec("bpy") is not None


def studio_hdris() -> dict[str, Path]:
    """Blender's bundled world HDRIs by name (studio, city, forest, ...)."""
    import importlib.util

    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        return {}
    root = Path(next(iter(spec.submodule_search_locations)))
    return {path.stem: path for path in sorted(root.glob("*/datafiles/studiolights/world/*.exr"))}


def _attenuation(distance: float) -> float:
    constant, linear, quadratic = ATTENUATION
    return constant + linear * distance + quadratic * distance * distance


def lamp_power(kind: str, position: torch.Tensor, intensity: torch.Tensor) -> float:
    """Blender lamp power (W; W/m^2 for a sun) that lights a Lambertian surface at the origin as our
    shader's diffuse term does (K_DIFFUSE x intensity / attenuation, docs/conventions.md): a point lamp
    gives radiance albedo x P / (4 pi^2 d^2), an area lamp facing the origin albedo x P / (pi^2 d^2), a
    sun albedo x S / pi."""
    distance = float(position.norm())
    factor = K_DIFFUSE * float(intensity.mean()) / _attenuation(distance)
    if kind == "point":
        return 4 * math.pi ** 2 * distance ** 2 * factor
    if kind == "area":
        return math.pi ** 2 * distance ** 2 * factor
    if kind == "sun":
        return math.pi * factor
    raise ValueError(kind)


@dataclass
class BlenderRenderer:
    """Renders with Blender's `engine` (cycles | eevee | workbench). `light`: point | sun | area (a lamp
    where our point light is, plus dim uniform world light for our ambient term) or world (only the
    `hdri` studio light); `samples`: per pixel (None: the engine's default here); `view_transform`:
    Standard or AgX (Blender's default); `roughness`/`specular`: the Principled BSDF's (a matte
    surface by default, like our shader's). Workbench lights with its own studio light whatever
    `light` says, as Blender does; `workbench_light` (STUDIO, Blender's default, or FLAT: the texture
    unlit), `workbench_specular` (the studio light's highlight), `dither` (the noise Blender adds before
    rounding to 8 bits, its `dither_intensity`) and `antialiasing` (Workbench's `render_aa`: OFF, FXAA,
    5, 8, 11, 16 or 32 samples) take Blender's defaults unless set, to measure what each costs the
    reading (experiments/engine_reading.py --blender)."""

    engine: str = "cycles"
    view_transform: str = "Standard"
    light: str = "point"
    samples: int | None = None
    hdri: str = "studio"
    roughness: float = 0.8
    specular: float = 0.0
    threads: int = 0
    seed: int = 0
    workbench_light: str = "STUDIO"
    workbench_specular: bool = True
    dither: float = 1.0
    antialiasing: str = "8"

    def __post_init__(self) -> None:
        if self.engine not in ENGINES:
            raise MeshsealError(f"unknown Blender engine '{self.engine}' ({' | '.join(ENGINES)})")
        if self.view_transform not in VIEW_TRANSFORMS:
            raise MeshsealError(f"unknown view transform '{self.view_transform}' ({' | '.join(VIEW_TRANSFORMS)})")
        if self.light not in LIGHT_KINDS:
            raise MeshsealError(f"unknown light '{self.light}' ({' | '.join(LIGHT_KINDS)})")
        if self.workbench_light not in ("STUDIO", "FLAT"):
            raise MeshsealError(f"unknown Workbench light '{self.workbench_light}' (STUDIO | FLAT)")
        if self.antialiasing not in ("OFF", "FXAA", "5", "8", "11", "16", "32"):
            raise MeshsealError(f"unknown Workbench antialiasing '{self.antialiasing}' (OFF | FXAA | 5 | 8 | 11 | 16 | 32)")
        if not available():
            raise MeshsealError("Blender rendering needs bpy: pip install 'meshseal[blender]' (bpy==5.0.1, Python 3.11)")
        if self.light == "world" and self.hdri not in studio_hdris():
            raise MeshsealError(f"unknown studio HDRI '{self.hdri}' ({' | '.join(studio_hdris())})")

    def _scene(self, mesh: Mesh, cameras: Cameras, lights: PointLights, width: int, height: int) -> dict:
        scene = {
            "engine": np.array(self.engine), "view_transform": np.array(self.view_transform),
            "width": np.array(width), "height": np.array(height),
            "samples": np.array(self.samples or DEFAULT_SAMPLES[self.engine]), "seed": np.array(self.seed),
            "threads": np.array(self.threads or os.cpu_count() or 1),
            "roughness": np.array(self.roughness), "specular_level": np.array(self.specular),
            "positions": mesh.positions.detach().cpu().numpy().astype(np.float64),
            "normals": mesh.normals.detach().cpu().numpy(),
            "faces": mesh.faces.cpu().numpy().astype(np.int64),
            "face_material": (mesh.face_material if mesh.face_material is not None
                              else torch.zeros(len(mesh.faces), dtype=torch.long)).cpu().numpy(),
            "diffuse": np.stack([m.diffuse.cpu().numpy() for m in mesh.materials]),
            "camera_to_world": torch.linalg.inv(cameras.view_matrix().double()).cpu().numpy(),
            "fov_y": np.array(cameras.fov_y), "principal": np.array(cameras.principal, dtype=np.float64),
            "light_kind": np.array(self.light),
            "workbench_light": np.array(self.workbench_light), "workbench_specular": np.array(self.workbench_specular),
            "dither": np.array(float(self.dither)), "antialiasing": np.array(self.antialiasing),
        }
        if mesh.uvs is not None:
            scene["uvs"] = mesh.uvs.detach().cpu().numpy()
        for index, material in enumerate(mesh.materials):
            if material.texture is not None:
                scene[f"texture_{index}"] = (material.texture.detach().clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
        ambient = K_AMBIENT * float(torch.stack([m.ambient.mean() for m in mesh.materials]).mean())
        if self.light == "world":
            scene["world_hdri"], scene["world_strength"] = np.array(str(studio_hdris()[self.hdri])), np.array(1.0)
            scene["light_position"], scene["light_power"] = np.zeros((len(cameras), 3)), np.zeros(len(cameras))
        else:
            scene["world_hdri"], scene["world_strength"] = np.array(""), np.array(ambient)
            first = lights.position[:, 0].detach().cpu()
            scene["light_position"] = first.double().numpy()
            scene["light_power"] = np.array([lamp_power(self.light, first[b], lights.intensity[b, 0].detach().cpu())
                                             for b in range(len(cameras))])
        return scene

    def render(self, mesh: Mesh, cameras: Cameras, lights: PointLights, width: int, height: int,
               background=(0.0, 0.0, 0.0)) -> torch.Tensor:
        """RGBA images (B, H, W, 4) in [0, 1], row 0 on top, the colour composited over `background`
        and alpha the coverage Blender reports."""
        from PIL import Image

        with tempfile.TemporaryDirectory(prefix="meshseal-blender-") as tmp:
            scene_path = Path(tmp) / "scene.npz"
            np.savez(scene_path, **self._scene(mesh, cameras, lights, width, height))
            done = subprocess.run([sys.executable, "-m", "meshseal.render.blender_worker", str(scene_path), tmp],
                                  capture_output=True, text=True, timeout=WORKER_TIMEOUT_S)
            if done.returncode != 0:
                last = (done.stderr.strip().splitlines() or ["(no message)"])[-1]
                raise MeshsealError(f"Blender ({self.engine}) failed: {last}")
            images = [np.asarray(Image.open(Path(tmp) / f"view_{k}.png").convert("RGBA"), dtype=np.float32) / 255.0
                      for k in range(len(cameras))]
        rgba = torch.from_numpy(np.stack(images))
        alpha = rgba[..., 3:]
        colour = rgba[..., :3] * alpha + torch.tensor(background, dtype=torch.float32) * (1 - alpha)
        return torch.cat([colour, alpha], dim=-1)
