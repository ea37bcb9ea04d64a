"""Rendering: cameras, lights, rasterizer, interpolation, textures, Phong shader, splatting, renderers.

Small composable primitives (like nvdiffrast's) laid out one file per stage (like PyTorch3D's), and a
`MeshRenderer` that composes them. External renderers implement the same `Renderer` protocol. The names
below are imported on first use (`meshseal._lazy`): the command line reads `ENGINES` without importing torch.
"""

from typing import TYPE_CHECKING

from .._lazy import export_lazily

if TYPE_CHECKING:
    from .renderer import Renderer

__all__ = ["Cameras", "cameras_from_eyes", "fibonacci_directions", "look_at", "perspective", "sample_any_view_cameras",
           "sample_seed_cameras", "interpolate", "scatter_to_image", "PointLights", "lights_at",
           "sample_any_lights", "sample_seed_lights", "Fragments", "clip_to_screen", "rasterize", "MeshBatch",
           "MeshRenderer", "Renderer", "RenderOutput", "PhongShader", "splat", "sample_texture",
           "sample_textures", "surface_points", "fit_point_light", "relight_fragments", "pixels_at", "surface_at_pixels", "surface_attributes",
           "unrender", "ENGINES", "LIGHT_KINDS", "VIEW_TRANSFORMS", "make_renderer"]

ENGINES = ("ours", "gl", "cycles", "eevee", "workbench")
VIEW_TRANSFORMS = ("Standard", "AgX")  # Blender engines
LIGHT_KINDS = ("point", "sun", "area", "world")  # Blender engines

_EXPORTS = {  # public name -> the submodule that defines it, imported on first use (meshseal._lazy)
    "Cameras": ".cameras", "cameras_from_eyes": ".cameras", "fibonacci_directions": ".cameras", "look_at": ".cameras", "perspective": ".cameras", "sample_any_view_cameras": ".cameras", "sample_seed_cameras": ".cameras",
    "interpolate": ".interpolate", "scatter_to_image": ".interpolate",
    "PointLights": ".lighting", "lights_at": ".lighting", "sample_any_lights": ".lighting", "sample_seed_lights": ".lighting",
    "Fragments": ".rasterizer", "clip_to_screen": ".rasterizer", "rasterize": ".rasterizer",
    "MeshBatch": ".renderer", "MeshRenderer": ".renderer", "Renderer": ".renderer", "RenderOutput": ".renderer",
    "PhongShader": ".shader",
    "splat": ".splatter",
    "sample_texture": ".texture", "sample_textures": ".texture",
    "fit_point_light": ".relight", "relight_fragments": ".relight",
    "surface_points": ".unrender", "pixels_at": ".unrender", "surface_at_pixels": ".unrender", "surface_attributes": ".unrender", "unrender": ".unrender",
}


def make_renderer(engine: str = "ours", **options) -> "Renderer":
    """The `Renderer` for `engine`: ours (the differentiable renderer; `blend` = splat | hard), gl
    (moderngl, the OpenGL reference) or a Blender engine (cycles | eevee | workbench; `options` as
    `BlenderRenderer` takes them)."""
    if engine == "ours":
        from .renderer import MeshRenderer

        return MeshRenderer(**options)
    if engine == "gl":
        from .opengl import OpenGLRenderer

        return OpenGLRenderer(**options)
    if engine in ("cycles", "eevee", "workbench"):
        from .blender import BlenderRenderer

        return BlenderRenderer(engine=engine, **options)
    raise ValueError(f"unknown engine '{engine}' ({' | '.join(ENGINES)})")


export_lazily(__name__, _EXPORTS)
