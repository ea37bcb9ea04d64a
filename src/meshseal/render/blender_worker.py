"""Renders a scene file with Blender (`bpy`) in its own process: `python -m meshseal.render.blender_worker
SCENE.npz OUT_DIR`. Writes OUT_DIR/view_K.png (RGBA, 8 bits, transparent background) for every camera.

Kept apart from `blender.py` (which writes the scene and reads the pictures back) because bpy brings
its own libraries and global state: a process of its own keeps them out of the caller's (torch's) way
and renders any number of views after one start-up. The scene follows docs/conventions.md: Z-up world,
OpenGL camera (looks down -Z, Y up), uv (0, 0) at the image's bottom-left, REPEAT wrapping.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

ENGINES = {"cycles": "CYCLES", "eevee": "BLENDER_EEVEE", "workbench": "BLENDER_WORKBENCH"}


def _reset(bpy) -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)


def _image(bpy, name: str, pixels: np.ndarray):
    """An 8-bit sRGB Blender image from (H, W, 3) uint8 pixels (row 0 on top)."""
    height, width = pixels.shape[:2]
    image = bpy.data.images.new(name, width, height, alpha=False)
    rgba = np.concatenate([pixels[::-1].astype(np.float32) / 255.0, np.ones((height, width, 1), np.float32)], axis=2)
    image.pixels.foreach_set(rgba.ravel())
    image.pack()
    return image


def _material(bpy, index: int, scene: dict, roughness: float):
    material = bpy.data.materials.new(f"material_{index}")
    material.use_nodes = True
    nodes = material.node_tree.nodes
    bsdf = nodes["Principled BSDF"]
    diffuse = scene["diffuse"][index]
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Specular IOR Level"].default_value = float(scene["specular_level"])
    key = f"texture_{index}"
    if key in scene:
        texture = nodes.new("ShaderNodeTexImage")
        texture.image = _image(bpy, key, scene[key])
        texture.interpolation = "Linear"
        texture.extension = "REPEAT"
        if np.allclose(diffuse, 1.0):
            material.node_tree.links.new(texture.outputs["Color"], bsdf.inputs["Base Color"])
        else:
            tint = nodes.new("ShaderNodeMix")
            tint.data_type, tint.blend_type = "RGBA", "MULTIPLY"
            tint.inputs["Factor"].default_value = 1.0
            tint.inputs[7].default_value = (*diffuse, 1.0)
            material.node_tree.links.new(texture.outputs["Color"], tint.inputs[6])
            material.node_tree.links.new(tint.outputs[2], bsdf.inputs["Base Color"])
    else:
        bsdf.inputs["Base Color"].default_value = (*diffuse, 1.0)
    return material


def _corner_normals(positions: np.ndarray, faces: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Each face corner's normal (F*3, 3), in Blender's loop order: the vertex normal, turned to the
    face's front (its winding) where it points behind. Our shading is two-sided and a vertex of a
    double-sided sheet (each triangle twinned with the opposite winding) has one normal for both
    twins; Blender shades a face seen from behind with its normal flipped, so the twin whose winding
    disagrees came out dark, and the two coincident twins z-fought in dark bands that neither our
    renderer nor Blender's own importers (whose files give each twin its own normal) show."""
    corners = positions[faces]  # (F, 3, 3)
    front = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # (F, 3)
    at_corner = normals[faces]  # (F, 3, 3)
    sign = np.where(np.einsum("fkc,fc->fk", at_corner, front) < 0, -1.0, 1.0)
    return (at_corner * sign[..., None]).reshape(-1, 3).astype(np.float32)


def _mesh_object(bpy, scene: dict, roughness: float):
    positions, faces = scene["positions"], scene["faces"]
    mesh = bpy.data.meshes.new("mesh")
    mesh.from_pydata(positions.tolist(), [], faces.tolist())
    mesh.update()
    if "uvs" in scene:
        layer = mesh.uv_layers.new(name="UVMap")
        layer.data.foreach_set("uv", scene["uvs"][faces.ravel()].astype(np.float32).ravel())
    mesh.polygons.foreach_set("use_smooth", np.ones(len(faces), dtype=bool))
    mesh.normals_split_custom_set(_corner_normals(positions, faces, scene["normals"]).tolist())
    for index in range(len(scene["diffuse"])):
        mesh.materials.append(_material(bpy, index, scene, roughness))
    mesh.polygons.foreach_set("material_index", scene["face_material"].astype(np.int32))
    mesh.update()
    obj = bpy.data.objects.new("mesh", mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _world(bpy, scene: dict) -> None:
    world = bpy.data.worlds.new("world")
    bpy.context.scene.world = world
    world.use_nodes = True
    background = world.node_tree.nodes["Background"]
    hdri = str(scene["world_hdri"])
    if hdri:
        environment = world.node_tree.nodes.new("ShaderNodeTexEnvironment")
        environment.image = bpy.data.images.load(hdri)
        world.node_tree.links.new(environment.outputs["Color"], background.inputs["Color"])
        background.inputs["Strength"].default_value = float(scene["world_strength"])
    else:
        ambient = float(scene["world_strength"])
        background.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
        background.inputs["Strength"].default_value = ambient


def _light(bpy, kind: str, position: np.ndarray, power: float):
    """A light of `kind` (point, sun, area) at `position`, turned toward the origin."""
    data = bpy.data.lights.new("light", type=kind.upper())
    if kind == "sun":
        data.energy = power
        data.angle = math.radians(1.0)
    else:
        data.energy = power
        data.shadow_soft_size = 0.05
        if kind == "area":
            data.size = 1.0
    obj = bpy.data.objects.new("light", data)
    bpy.context.scene.collection.objects.link(obj)
    obj.location = position.tolist()
    direction = -position / max(np.linalg.norm(position), 1e-9)
    obj.rotation_mode = "QUATERNION"
    obj.rotation_quaternion = _look_rotation(direction)
    return obj


def _look_rotation(direction: np.ndarray):
    """The quaternion turning -Z (where Blender's lights and cameras point) onto `direction`."""
    from mathutils import Vector

    return Vector((0.0, 0.0, -1.0)).rotation_difference(Vector(direction.tolist()))


def _camera(bpy, width: int, height: int):
    data = bpy.data.cameras.new("camera")
    data.sensor_fit = "VERTICAL"
    data.clip_start, data.clip_end = 0.1, 100.0
    obj = bpy.data.objects.new("camera", data)
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.scene.camera = obj
    return obj


def _set_camera(obj, camera_to_world: np.ndarray, fov_y: float, principal, width: int, height: int) -> None:
    from mathutils import Matrix

    obj.matrix_world = Matrix(camera_to_world.tolist())
    obj.data.angle_y = math.radians(fov_y)
    # With a vertical sensor fit Blender's shift is a fraction of the picture's height (measured);
    # `principal` is in NDC (-1..1 across each side).
    obj.data.shift_x = -float(principal[0]) * width / (2 * height)
    obj.data.shift_y = -float(principal[1]) / 2


def _settings(bpy, scene: dict, width: int, height: int) -> None:
    render_scene = bpy.context.scene
    engine = str(scene["engine"])
    render_scene.render.engine = ENGINES[engine]
    render_scene.render.resolution_x, render_scene.render.resolution_y = width, height
    render_scene.render.resolution_percentage = 100
    render_scene.render.film_transparent = True
    render_scene.render.image_settings.file_format = "PNG"
    render_scene.render.image_settings.color_mode = "RGBA"
    render_scene.render.image_settings.color_depth = "8"
    render_scene.view_settings.view_transform = str(scene["view_transform"])
    render_scene.view_settings.look = "None"
    render_scene.render.threads_mode = "FIXED"
    render_scene.render.threads = int(scene["threads"])
    render_scene.render.dither_intensity = float(scene["dither"])
    samples = int(scene["samples"])
    if engine == "cycles":
        render_scene.cycles.device = "CPU"
        render_scene.cycles.samples = samples
        render_scene.cycles.use_adaptive_sampling = False
        render_scene.cycles.use_denoising = False
        render_scene.cycles.seed = int(scene["seed"])
        render_scene.cycles.max_bounces = 4
    elif engine == "eevee":
        render_scene.eevee.taa_render_samples = samples
    else:
        shading = render_scene.display.shading
        shading.light = str(scene["workbench_light"])
        shading.show_specular_highlight = bool(scene["workbench_specular"])
        shading.color_type = "TEXTURE"
        render_scene.display.render_aa = str(scene["antialiasing"])


def main(scene_path: str, out_dir: str) -> int:
    import bpy

    scene = dict(np.load(scene_path, allow_pickle=False))
    _reset(bpy)
    width, height = int(scene["width"]), int(scene["height"])
    _settings(bpy, scene, width, height)
    _mesh_object(bpy, scene, float(scene["roughness"]))
    _world(bpy, scene)
    camera = _camera(bpy, width, height)
    kind = str(scene["light_kind"])
    light = _light(bpy, kind, scene["light_position"][0], float(scene["light_power"][0])) if kind != "world" else None
    out = Path(out_dir)
    for view in range(len(scene["camera_to_world"])):
        _set_camera(camera, scene["camera_to_world"][view], float(scene["fov_y"]), scene["principal"], width, height)
        if light is not None:
            light.location = scene["light_position"][view].tolist()
            light.rotation_quaternion = _look_rotation(-scene["light_position"][view] /
                                                       max(np.linalg.norm(scene["light_position"][view]), 1e-9))
            light.data.energy = float(scene["light_power"][view])
        bpy.context.scene.render.filepath = str(out / f"view_{view}.png")
        bpy.ops.render.render(write_still=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
