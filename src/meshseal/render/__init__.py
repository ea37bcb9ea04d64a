"""Rendering: cameras, lights, rasterizer, interpolation, textures, Phong shader, splatting, renderers.

Small composable primitives (like nvdiffrast's) laid out one file per stage (like PyTorch3D's), and a
`MeshRenderer` that composes them. External renderers implement the same `Renderer` protocol.
"""

from .cameras import Cameras, cameras_from_eyes, fibonacci_directions, look_at, perspective, sample_any_view_cameras, sample_seed_cameras
from .interpolate import interpolate, scatter_to_image
from .lighting import PointLights, lights_at, sample_any_lights, sample_seed_lights
from .rasterizer import Fragments, clip_to_screen, rasterize
from .renderer import MeshBatch, MeshRenderer, Renderer, RenderOutput
from .shader import PhongShader
from .splatter import splat
from .texture import sample_texture, sample_textures
from .relight import fit_point_light, relight_fragments
from .unrender import surface_points, pixels_at, surface_at_pixels, surface_attributes, unrender

__all__ = ["Cameras", "cameras_from_eyes", "fibonacci_directions", "look_at", "perspective", "sample_any_view_cameras",
           "sample_seed_cameras", "interpolate", "scatter_to_image", "PointLights", "lights_at",
           "sample_any_lights", "sample_seed_lights", "Fragments", "clip_to_screen", "rasterize", "MeshBatch",
           "MeshRenderer", "Renderer", "RenderOutput", "PhongShader", "splat", "sample_texture",
           "sample_textures", "surface_points", "fit_point_light", "relight_fragments", "pixels_at", "surface_at_pixels", "surface_attributes",
           "unrender", "ENGINES", "make_renderer"]

ENGINES = ("ours", "gl", "cycles", "eevee", "workbench")


def make_renderer(engine: str = "ours", **options) -> Renderer:
    """The `Renderer` for `engine`: ours (the differentiable renderer; `blend` = splat | hard), gl
    (moderngl, the OpenGL reference) or a Blender engine (cycles | eevee | workbench; `options` as
    `BlenderRenderer` takes them)."""
    if engine == "ours":
        return MeshRenderer(**options)
    if engine == "gl":
        from .opengl import OpenGLRenderer

        return OpenGLRenderer(**options)
    if engine in ("cycles", "eevee", "workbench"):
        from .blender import BlenderRenderer

        return BlenderRenderer(engine=engine, **options)
    raise ValueError(f"unknown engine '{engine}' ({' | '.join(ENGINES)})")
