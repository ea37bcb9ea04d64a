"""Load meshes from real files through trimesh and write changes back into the same structure.

Design: a file is loaded as a trimesh Scene. Every (node, geometry) instance becomes a *part*; parts are
concatenated into one `Mesh` with a per-face material index (one material per trimesh geometry, with
its own texture). Saving copies the Scene, writes each part's normals, uvs, texture (and positions, if
they changed) back into its geometry and exports in the input's format, so material names, other maps
(normal, metallic-roughness, ...), node names and transforms survive. An OBJ is then put back in its
source's terms (`_obj_as_source`): object and group names, the MTL's fields as written, texture names
and formats.
"""

from __future__ import annotations

import copy
import io
import os
import re
import stat
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from ..errors import MeshError
from ..mesh_formats import file_type as _file_type
from . import cache as mesh_cache
from .files import atomic_write_files
from .core import DEFAULT_AMBIENT, DEFAULT_DIFFUSE, Material, Mesh
from .preprocess import vertex_normals
from .validate import (check_glb, check_gltf, check_images, check_obj, check_off, check_ply, check_stl,
                       find_asset, read_regular, regular_file, resolved)

TEXT_FORMATS = {"obj", "off", "gltf"}
STRUCTURE_CHECKS = {"glb": check_glb, "gltf": check_gltf, "ply": check_ply, "off": check_off, "stl": check_stl}
UP_AXIS = {"obj": "y", "glb": "y", "gltf": "y", "ply": "z", "off": "z", "stl": "z"}


@dataclass
class Part:
    """Where one scene instance lives in the concatenated Mesh."""

    node: str
    geometry: str
    vertices: slice
    faces: slice
    transform: np.ndarray


@dataclass
class Source:
    """The loaded file: kept so that saving writes changes back into the same structure."""

    path: Path
    file_type: str
    scene: object
    parts: list[Part]
    original_positions: torch.Tensor
    input_files: set[Path]


def _warn(message: str) -> None:
    print(f"meshseal: warning: {message}", file=sys.stderr)


def _obj_references(path: Path, data: bytes) -> tuple[list[str], set[Path], list[tuple[str, Path]]]:
    """What an OBJ's MTL libraries name, resolved as trimesh resolves them: the names not found, the
    files found, and the diffuse textures (map_Kd, the ones trimesh reads) to decode-check. A referenced
    file that is not a regular file (a pipe, a device) is an error: reading it could block forever."""
    missing, present, textures = [], set(), []
    text = data.decode("utf-8", "replace")
    for mtl_name in re.findall(r"^\s*mtllib\s+(.+?)\s*$", text, flags=re.M):
        mtl_path = find_asset(path.parent, mtl_name)
        if mtl_path is None:
            missing.append(mtl_name)
            continue
        present.add(mtl_path)
        for line in read_regular(mtl_path, "material file").decode("utf-8", "replace").splitlines():
            fields = line.strip().split()
            if len(fields) < 2 or not fields[0].lower().startswith("map_"):
                continue
            name = line.strip()[len(fields[0]):].strip() if fields[0].lower() == "map_kd" else fields[-1]
            image = find_asset(mtl_path.parent, name)
            if image is None:
                missing.append(name)
                continue
            regular_file(image, "texture file")
            present.add(image)
            if fields[0].lower() == "map_kd":
                textures.append((f"{mtl_path.parent / name}", image))
    return missing, present, textures


def _image_to_tensor(image) -> torch.Tensor | None:
    if image is None:
        return None
    if not isinstance(image, Image.Image):
        return None
    array = np.asarray(image.convert("RGB"), dtype=np.float32) / 255.0
    return torch.from_numpy(array.copy())


def _file_normals(geometry) -> np.ndarray | None:
    """The vertex normals stored in the file, if it had usable ones (trimesh keeps them in its cache)."""
    cache = getattr(getattr(geometry, "_cache", None), "cache", {})
    normals = cache.get("vertex_normals")
    if normals is None or len(normals) != len(geometry.vertices):
        return None
    normals = np.asarray(normals, dtype=np.float64)
    if not np.isfinite(normals).all() or (np.linalg.norm(normals, axis=1) < 0.5).any():
        return None
    return normals


def _material(visual, name: str) -> Material:
    """The seed's material block from a trimesh visual (Simple or PBR material)."""
    result = Material(name=name)
    material = getattr(visual, "material", None)
    if material is None:
        return result
    result.name = getattr(material, "name", None) or name
    if hasattr(material, "baseColorFactor"):  # PBR (glTF)
        factor = material.baseColorFactor
        if factor is not None:
            result.diffuse = torch.tensor(np.asarray(factor, dtype=np.float32)[:3] / 255.0)
        result.texture = _image_to_tensor(material.baseColorTexture)
    else:
        for key in ("ambient", "diffuse", "specular"):
            value = getattr(material, key, None)
            if value is not None:
                setattr(result, key, torch.tensor(np.asarray(value, dtype=np.float32)[:3] / 255.0))
        # An MTL with Ka 0 0 0 would render ambient-black; keep the seed's ambient term meaningful.
        if float(result.ambient.max()) == 0.0:
            result.ambient = torch.full((3,), DEFAULT_AMBIENT)
        if getattr(material, "glossiness", None) is not None:
            result.shininess = float(material.glossiness)
        result.texture = _image_to_tensor(material.image)
    if result.texture is not None and float(result.diffuse.max()) == 0.0:
        result.diffuse = torch.full((3,), DEFAULT_DIFFUSE)
    texture = result.texture
    if texture is not None and texture.shape[0] * texture.shape[1] <= 4 and bool((texture == texture[0, 0]).all()):
        # A uniform placeholder (trimesh invents a 2x2 grey image for UVs without a material):
        # a flat colour, not a texture. Rendering is unchanged (albedo = texture * diffuse).
        result.diffuse = result.diffuse * texture[0, 0]
        result.texture = None
    return result


def load(path, up_axis: str | None = None, cache: bool | str = False) -> Mesh:
    """Load a mesh file (OBJ+MTL+images, GLB/glTF, PLY, OFF, STL) as one concatenated `Mesh`.

    Raises MeshError with a one-line message for anything unusable. A texture file that is missing
    is a warning: the material falls back to its flat diffuse colour.
    `cache` (`mesh.cache`): True for a caller that only reads the mesh: the same input loaded before
    comes from the cache, without trimesh (its source then has no scene: it cannot be saved), and a
    first load fills it; "fill" loads with trimesh as always and fills the cache for later readers.
    A glTF, or a GLB that names files outside itself, is not cached.
    """
    path = Path(path)
    file_type = _file_type(path)
    data = read_regular(path, "mesh file")
    if not data:
        raise MeshError(f"{path}: file is empty")
    if file_type in TEXT_FORMATS and b"\x00" in data[:1 << 16]:
        raise MeshError(f"{path}: binary data, not a text {file_type.upper()} file")
    input_files = {resolved(path, 'mesh file')}
    images: list = []
    if file_type == "obj":
        check_obj(path, data)
        missing, present, images = _obj_references(path, data)
        input_files |= present
        for name in missing:
            _warn(f"{path}: texture or material file '{name}' not found; using the flat diffuse colour")
    elif file_type in STRUCTURE_CHECKS:
        images = STRUCTURE_CHECKS[file_type](path, data) or []
        for name, image in images:
            if image is None:
                _warn(f"{name} not found; using the flat diffuse colour")
    check_images(images)
    entry = None
    if cache and file_type != "gltf" and not (file_type == "glb" and mesh_cache.glb_external(data)):
        entry = mesh_cache.key(path, data, file_type, up_axis or UP_AXIS[file_type], input_files)
        stored = mesh_cache.read(entry) if cache is True else None
        if stored is not None:
            try:
                return _from_cache(*stored, path, file_type, input_files)
            except Exception:  # noqa: BLE001 - an entry of another layout: loaded afresh below
                pass
    import trimesh

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scene = trimesh.load(str(path), file_type=file_type, force="scene", process=False)
    except MeshError:
        raise
    except Exception as error:  # trimesh raises many kinds on corrupt input
        detail = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        if "unexpected length" in detail:  # trimesh's binary PLY length check
            detail = "the binary data's length does not match the header's element counts (cut off?)"
        if isinstance(error, ModuleNotFoundError) and error.name == "charset_normalizer":
            detail = "not UTF-8 text (install charset-normalizer to read other text encodings)"
        raise MeshError(f"{path}: cannot read as {file_type.upper()}: {detail[:200]}") from None
    if file_type == "gltf":
        input_files |= {resolved(p) for p in path.parent.iterdir() if p.suffix.lower() in
                        {".bin", ".png", ".jpg", ".jpeg", ".webp"}}
    mesh = _from_scene(scene, path, file_type, input_files, up_axis or UP_AXIS[file_type])
    if entry is not None:
        mesh_cache.write(entry, *_for_cache(mesh))
    return mesh


def _for_cache(mesh: Mesh) -> tuple[dict, dict]:
    """A loaded mesh as a cache entry (`mesh.cache`): a JSON header and tensors."""
    tensors = {"positions": mesh.positions, "normals": mesh.normals, "faces": mesh.faces,
               "face_material": mesh.face_material}
    if mesh.uvs is not None:
        tensors["uvs"] = mesh.uvs
    materials = []
    for number, material in enumerate(mesh.materials):
        materials.append({"name": material.name, "shininess": material.shininess})
        for field in ("ambient", "diffuse", "specular"):
            tensors[f"{field}{number}"] = getattr(material, field)
        if material.texture is not None:
            tensors[f"texture{number}"] = mesh_cache.eight_bit(material.texture)
    parts = [{"node": p.node, "geometry": p.geometry, "vertices": [p.vertices.start, p.vertices.stop],
              "faces": [p.faces.start, p.faces.stop], "transform": np.asarray(p.transform).tolist()}
             for p in mesh.source.parts]
    return {"materials": materials, "up_axis": mesh.up_axis, "parts": parts}, tensors


def _from_cache(header: dict, tensors: dict, path: Path, file_type: str, input_files: set[Path]) -> Mesh:
    """`_for_cache`'s entry as the Mesh it was made from; its source has the parts and no scene."""
    materials = [Material(name=fields["name"], texture=mesh_cache.from_eight_bit(tensors[f"texture{number}"])
                          if f"texture{number}" in tensors else None,
                          ambient=tensors[f"ambient{number}"], diffuse=tensors[f"diffuse{number}"],
                          specular=tensors[f"specular{number}"], shininess=float(fields["shininess"]))
                 for number, fields in enumerate(header["materials"])]
    mesh = Mesh(positions=tensors["positions"], normals=tensors["normals"], faces=tensors["faces"],
                uvs=tensors.get("uvs"), face_material=tensors["face_material"], materials=materials,
                up_axis=header["up_axis"])
    parts = [Part(p["node"], p["geometry"], slice(*p["vertices"]), slice(*p["faces"]),
                  np.asarray(p["transform"], dtype=np.float64)) for p in header["parts"]]
    mesh.source = Source(path, file_type, None, parts, mesh.positions.clone(), input_files)
    return mesh


def _from_scene(scene, path: Path, file_type: str, input_files: set[Path], up_axis: str) -> Mesh:
    import trimesh

    positions, normals, uvs, faces, face_material = [], [], [], [], []
    materials: list[Material] = []
    material_index: dict[int, int] = {}
    parts: list[Part] = []
    n_vertices = n_faces = 0
    any_uv = False
    # Parts in node-name order: trimesh's own order depends on the format (OBJ comes back reversed) and
    # flips on every save/load; node names survive saving, so this keeps vertex order across round trips.
    for node in sorted(scene.graph.nodes_geometry, key=str):
        transform, geometry_name = scene.graph[node]
        geometry = scene.geometry.get(geometry_name)
        if not isinstance(geometry, trimesh.Trimesh) or len(geometry.faces) == 0:
            continue
        vertices = np.asarray(geometry.vertices, dtype=np.float64)
        triangles = np.asarray(geometry.faces, dtype=np.int64)
        if not np.isfinite(vertices).all():
            raise MeshError(f"{path}: vertex positions contain NaN or infinity (in '{geometry_name}')")
        if triangles.min() < 0 or triangles.max() >= len(vertices):
            raise MeshError(f"{path}: face indices out of range (in '{geometry_name}', "
                            f"{len(vertices)} vertices)")
        world = vertices @ transform[:3, :3].T + transform[:3, 3]
        normal_matrix = np.linalg.inv(transform[:3, :3]).T
        local_normals = _file_normals(geometry)
        if local_normals is None:
            local_normals = vertex_normals(torch.from_numpy(vertices), torch.from_numpy(triangles)).numpy()
        world_normals = local_normals @ normal_matrix.T
        world_normals /= np.maximum(np.linalg.norm(world_normals, axis=1, keepdims=True), 1e-12)
        uv = getattr(geometry.visual, "uv", None)
        if uv is not None and len(uv) == len(vertices) and np.isfinite(uv).all():
            any_uv = True
            uvs.append(np.asarray(uv, dtype=np.float64))
        else:
            uvs.append(np.zeros((len(vertices), 2)))
        key = id(getattr(geometry.visual, "material", None) or geometry)
        if key not in material_index:
            material_index[key] = len(materials)
            materials.append(_material(geometry.visual, geometry_name))
        positions.append(world)
        normals.append(world_normals)
        faces.append(triangles + n_vertices)
        face_material.append(np.full(len(triangles), material_index[key], dtype=np.int64))
        parts.append(Part(str(node), geometry_name, slice(n_vertices, n_vertices + len(vertices)),
                          slice(n_faces, n_faces + len(triangles)), np.asarray(transform)))
        n_vertices += len(vertices)
        n_faces += len(triangles)
    if n_faces == 0:
        raise MeshError(f"{path}: contains no triangle faces")
    position_tensor = torch.from_numpy(np.concatenate(positions)).float()
    mesh = Mesh(
        positions=position_tensor,
        normals=torch.from_numpy(np.concatenate(normals)).float(),
        faces=torch.from_numpy(np.concatenate(faces)),
        uvs=torch.from_numpy(np.concatenate(uvs)).float() if any_uv else None,
        face_material=torch.from_numpy(np.concatenate(face_material)),
        materials=materials or [Material()],
        up_axis=up_axis,
    )
    mesh.source = Source(path, file_type, scene, parts, position_tensor.clone(), input_files)
    return mesh


# ---------------------------------------------------------------- saving


def _tensor_to_image(texture: torch.Tensor, like) -> Image.Image:
    array = (texture.detach().clamp(0, 1).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)
    image = Image.fromarray(array, "RGB")
    if isinstance(like, Image.Image) and like.mode in ("RGBA", "LA"):
        alpha = like.getchannel("A")
        if like.size != image.size:  # charted (`methods.charts`): the old texels top left, the charts opaque
            grown = Image.new("L", image.size, 255)
            grown.paste(alpha, (0, 0))
            alpha = grown
        image.putalpha(alpha)
    return image


def _write_back(mesh: Mesh) -> object:
    """A copy of the source scene with the mesh's attributes written into its geometries."""
    source: Source = mesh.source
    scene = copy.deepcopy(source.scene)
    # Charts (`methods.charts`) add vertices, copies of others: those parts are rebuilt, the rest keep theirs.
    positions_changed = (mesh.positions.shape == source.original_positions.shape
                         and not torch.equal(mesh.positions.detach().cpu(), source.original_positions))
    done: set[str] = set()
    for part in source.parts:
        if part.geometry in done:  # an instanced geometry is written from its first instance
            continue
        done.add(part.geometry)
        geometry = scene.geometry[part.geometry]
        inverse = np.linalg.inv(part.transform)
        rebuilt = part.vertices.stop - part.vertices.start != len(geometry.vertices)
        if rebuilt:
            geometry = _rebuilt(geometry, mesh, part)
            scene.geometry[part.geometry] = geometry
        if positions_changed or rebuilt:
            world = mesh.positions[part.vertices].detach().cpu().double().numpy()
            geometry.vertices = world @ inverse[:3, :3].T + inverse[:3, 3]
        world_normals = mesh.normals[part.vertices].detach().cpu().double().numpy()
        local = world_normals @ part.transform[:3, :3]  # inverse of the inverse-transpose
        local /= np.maximum(np.linalg.norm(local, axis=1, keepdims=True), 1e-12)
        geometry.vertex_normals = local
        visual = geometry.visual
        if mesh.uvs is not None and hasattr(visual, "uv"):
            visual.uv = mesh.uvs[part.vertices].detach().cpu().double().numpy()
        material_id = int(mesh.face_material[part.faces.start]) if part.faces.stop > part.faces.start else 0
        texture = mesh.materials[material_id].texture
        material = getattr(visual, "material", None)
        if texture is not None and material is not None:
            if hasattr(material, "baseColorTexture"):
                material.baseColorTexture = _tensor_to_image(texture, material.baseColorTexture)
            elif hasattr(material, "image"):
                material.image = _tensor_to_image(texture, material.image)
    return scene


def _rebuilt(geometry, mesh: Mesh, part):
    """A part's geometry with the mesh's vertices and faces for it (`methods.charts` added vertices),
    its material kept; positions, normals and UVs are written as for any part."""
    import trimesh

    faces = (mesh.faces[part.faces] - part.vertices.start).cpu().numpy()
    vertices = np.zeros((part.vertices.stop - part.vertices.start, 3))
    material = getattr(geometry.visual, "material", None)
    visual = trimesh.visual.TextureVisuals(uv=np.zeros((len(vertices), 2)), material=material)
    return trimesh.Trimesh(vertices=vertices, faces=faces, visual=visual, process=False)


def _normal_keeping_scene(scene):
    """The same scene, but its dump() keeps each geometry's vertex normals (see _export)."""
    import trimesh

    class NormalKeepingScene(trimesh.Scene):
        def dump(self, concatenate: bool = False):
            result = []
            for node in self.graph.nodes_geometry:
                transform, name = self.graph[node]
                geometry = self.geometry[name]
                if not isinstance(geometry, trimesh.Trimesh):
                    continue
                current = geometry.copy(include_cache=True)  # keeps the vertex normals
                current.apply_transform(transform)  # transforms them along
                current.metadata["name"] = name
                current.metadata["node"] = node
                result.append(current)
            return result

    copied = copy.copy(scene)
    copied.__class__ = NormalKeepingScene
    return copied


def _export(scene, file_type: str, stem: str) -> dict[str, bytes]:
    """The exported files as {relative name: bytes}."""
    import trimesh
    from trimesh.exchange.obj import export_obj

    if file_type == "obj":
        # trimesh's OBJ exporter bakes the scene with Scene.dump(), whose geometry copies drop cached
        # data, vertex normals included (they would be recomputed from the faces): keep them.
        scene = _normal_keeping_scene(scene)
        text, extra = export_obj(scene, include_normals=True, include_texture=True, return_texture=True,
                                 mtl_name=f"{stem}.mtl", header="meshseal")
        files = {f"{stem}.obj": text.encode()}
        renames = {name: f"{stem}_{name}" for name in extra if name != f"{stem}.mtl"}
        for name, data in extra.items():
            if name == f"{stem}.mtl":
                mtl = data.decode()
                for old, new in renames.items():
                    mtl = re.sub(rf"(?<=\s){re.escape(old)}(?=\s|$)", new, mtl)
                files[name] = mtl.encode()
            else:
                files[renames[name]] = data
        return files
    if file_type == "glb":
        return {f"{stem}.glb": trimesh.exchange.gltf.export_glb(scene, include_normals=True)}
    if file_type == "gltf":
        exported = trimesh.exchange.gltf.export_gltf(scene, include_normals=True)
        return {(f"{stem}.gltf" if name == "model.gltf" else name): data for name, data in exported.items()}
    geometry = scene.to_geometry() if hasattr(scene, "to_geometry") else scene.dump(concatenate=True)
    data = geometry.export(file_type=file_type)
    return {f"{stem}.{file_type}": data if isinstance(data, bytes) else data.encode()}


JPEG_QUALITY = 95  # a marked texture read from a JPEG is written as JPEG at this quality, 4:4:4 chroma


def _obj_records(text: str) -> tuple[list[str], dict[str, tuple[str | None, str | None]]]:
    """An OBJ's `mtllib` names and, for each material its `usemtl` records name, the object (`o`) and
    group (`g`) it is first used in (None where the file has none)."""
    libraries, objects, current = [], {}, {"o": None, "g": None}
    for line in text.splitlines():
        fields = line.strip().split(None, 1)
        if not fields:
            continue
        rest = fields[1].strip() if len(fields) > 1 else ""
        if fields[0] in ("o", "g"):
            current[fields[0]] = rest
        elif fields[0] == "usemtl":
            objects.setdefault(rest, (current["o"], current["g"]))
        elif fields[0] == "mtllib":
            libraries.append(rest)
    return libraries, objects


def _mtl_blocks(text: str) -> dict[str, list[str]]:
    """An MTL's material blocks, {name: its lines, `newmtl` first}; a name defined twice keeps the last."""
    blocks, name = {}, None
    for line in text.splitlines():
        fields = line.strip().split(None, 1)
        if fields and fields[0] == "newmtl":
            name = fields[1].strip() if len(fields) > 1 else ""
            blocks[name] = []
        if name is not None and line.strip():
            blocks[name].append(line.rstrip())
    return blocks


def _map_kd(lines: list[str]) -> str | None:
    """The texture file a material block's `map_Kd` names (the rest of the line, as trimesh reads it)."""
    for line in lines:
        fields = line.strip().split()
        if len(fields) >= 2 and fields[0].lower() == "map_kd":
            return line.strip()[len(fields[0]):].strip()
    return None


def _obj_as_source(files: dict[str, bytes], source: Source, path: Path) -> dict[str, bytes]:
    """trimesh's OBJ export of a loaded OBJ, put back in the source's terms: each material's block as the
    source MTL wrote it (every field: Ni, d, illum, other maps...) with only its diffuse texture renamed;
    the marked texture named as the source's with a suffix (the output's name past the input's, e.g.
    `wood.jpg` -> `wood_marked.jpg` for `chair.obj` -> `chair_marked.obj`, else `_` and the output's
    name) and in its format (a JPEG as JPEG at JPEG_QUALITY with full-resolution chroma; PNG for any
    other format or a texture with alpha); the source's object and group names (`o`, `g`) instead of
    the per-material objects trimesh writes; other maps the MTL names copied beside the output under
    their base names. A material the source does not define keeps trimesh's block."""
    stem = path.stem
    libraries, objects = _obj_records(read_regular(source.path, "mesh file").decode("utf-8", "replace"))
    blocks: dict[str, tuple[list[str], Path]] = {}
    for library in libraries:
        mtl_path = find_asset(source.path.parent, library)
        if mtl_path is not None:
            text = read_regular(mtl_path, "material file").decode("utf-8", "replace")
            blocks |= {name: (lines, mtl_path.parent) for name, lines in _mtl_blocks(text).items()}
    exported = _mtl_blocks(files.get(f"{stem}.mtl", b"").decode())
    suffix = stem[len(source.path.stem):] if stem.startswith(source.path.stem) else f"_{stem}"
    result = {f"{stem}.obj": files[f"{stem}.obj"]}
    taken: dict[str, bytes] = {}
    mtl_lines = ["# meshseal"]
    order = list(blocks)  # the source's order of materials, trimesh's for any other
    for name, lines in sorted(exported.items(), key=lambda item: order.index(item[0]) if item[0] in order else len(order)):
        texture = _map_kd(lines)
        if name not in blocks:
            if texture is not None:
                result[texture] = files[texture]
            mtl_lines += ["", *lines]
            continue
        original, folder = blocks[name]
        new_lines = []
        for line in original:
            fields = line.strip().split()
            keyword = fields[0].lower() if fields else ""
            if keyword == "map_kd" and texture is not None:
                data, new_name = _texture_as_source(files[texture], _map_kd(original), suffix)
                if taken.get(new_name, data) != data:  # two materials named one file: each keeps its own
                    new_name = f"{Path(new_name).stem}_{name}{Path(new_name).suffix}"
                taken[new_name] = result[new_name] = data
                line = f"map_Kd {new_name}"
            elif keyword.startswith("map_") or keyword in ("bump", "disp", "decal", "refl", "norm"):
                found = find_asset(folder, fields[-1]) if len(fields) >= 2 else None
                if found is not None:
                    base = Path(fields[-1].replace("\\", "/")).name
                    line = line.rstrip()[: line.rstrip().rindex(fields[-1])] + base
                    if resolved(path.parent / base) != found:
                        result[base] = read_regular(found, "texture file")
            new_lines.append(line)
        if texture is not None and _map_kd(original) is None:  # trimesh found a texture the block does not name
            result[texture] = files[texture]
            new_lines.append(f"map_Kd {texture}")
        mtl_lines += ["", *new_lines]
    if exported:
        result[f"{stem}.mtl"] = ("\n".join(mtl_lines) + "\n").encode()
    result[f"{stem}.obj"] = _obj_names_as_source(result[f"{stem}.obj"].decode(), objects).encode()
    return result


def _texture_as_source(png: bytes, source_name: str, suffix: str) -> tuple[bytes, str]:
    """A marked texture (trimesh's PNG bytes) named and encoded as the source's `source_name` was."""
    name = Path(source_name.replace("\\", "/"))
    image = Image.open(io.BytesIO(png))
    if name.suffix.lower() in (".jpg", ".jpeg") and image.mode in ("RGB", "L"):
        buffer = io.BytesIO()
        image.save(buffer, format="JPEG", quality=JPEG_QUALITY, subsampling=0)
        return buffer.getvalue(), f"{name.stem}{suffix}{name.suffix}"
    return png, f"{name.stem}{suffix}.png"


def _obj_names_as_source(text: str, objects: dict[str, tuple[str | None, str | None]]) -> str:
    """trimesh's OBJ text with its `o MATERIAL` lines replaced by the source's object and group names
    for that material (each written where it changes, as the source had them; none where it had none)."""
    lines, out, pending, written = text.split("\n"), [], None, (None, None)
    for line in lines:
        if line.startswith("o "):
            pending = line
            continue
        if pending is not None and line.startswith("usemtl "):
            material = line[len("usemtl "):].strip()
            names = objects.get(material)
            if names is None:
                out.append(pending)
            else:
                if names[0] is not None and names[0] != written[0]:
                    out.append(f"o {names[0]}")
                if names[1] is not None and names[1] != written[1]:
                    out.append(f"g {names[1]}")
                written = names
            pending = None
        elif pending is not None:
            out.append(pending)
            pending = None
        out.append(line)
    return "\n".join(out)


def check_output(path: Path, inputs=()) -> None:
    """Refuse, before any work, an output path a careful tool must not write: one that is an input,
    resolves to one (a symbolic link) or is a hard link to one (same device and inode); an existing
    folder or special file (a pipe, a device: replacing it is never meant); a path under a file; a
    folder that cannot be written. A missing folder is fine: `atomic_write` creates it."""
    path = Path(path)
    for source in inputs:
        try:
            same = path.resolve() == Path(source).resolve() or os.path.samefile(path, source)
        except (OSError, RuntimeError):  # the output does not exist yet (or the input is gone, or the
            same = False  # output is a symbolic link loop, replaced by the file): not the same file
        if same:
            raise MeshError(f"{path}: refusing to overwrite an input file ({Path(source).name}); "
                            f"choose another output path")
    if os.path.lexists(path):
        mode = os.stat(path).st_mode if os.path.exists(path) else os.lstat(path).st_mode
        if stat.S_ISDIR(mode):
            raise MeshError(f"{path}: is a directory")
        if not stat.S_ISREG(mode) and not stat.S_ISLNK(mode):
            raise MeshError(f"{path}: exists and is not a regular file; refusing to replace it")
    folder = path.parent
    while not folder.exists():
        if os.path.lexists(folder):
            raise MeshError(f"{folder}: is a broken symbolic link, cannot create the output folder")
        folder = folder.parent
    if not folder.is_dir():
        raise MeshError(f"{folder}: is not a directory, cannot write {path.name} under it")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise MeshError(f"{folder}: folder is not writable (permission denied)")


def save(mesh: Mesh, path) -> list[Path]:
    """Save `mesh` in the format of `path`; returns the files written.

    A mesh loaded from a file is written back into that file's structure (its format must match the
    output's). Never overwrites any of the input's files. Every file is written atomically.
    """
    import trimesh

    path = Path(path)
    file_type = _file_type(path)
    source: Source | None = mesh.source
    if source is not None:
        if source.scene is None:
            raise MeshError(f"{source.path}: this mesh came from the load cache, which keeps no file structure to "
                            "write back into: load it with `cache=False` to save it")
        if source.file_type != file_type and not (source.file_type in ("glb", "gltf") and file_type in ("glb", "gltf")):
            raise MeshError(f"{path}: output format must match the input's ({source.path.suffix})")
        scene = _write_back(mesh)
    else:
        scene = trimesh.Scene(_to_trimesh(mesh))
    files = _export(scene, file_type, path.stem)
    if file_type == "obj" and source is not None:
        files = _obj_as_source(files, source, path)
    targets = {path.parent / name: data for name, data in files.items()}
    for target in targets:
        check_output(target, source.input_files if source is not None else ())
    atomic_write_files(targets)
    return list(targets)


def _to_trimesh(mesh: Mesh):
    """A trimesh geometry for a Mesh built in memory (single material)."""
    import trimesh

    visual = None
    if mesh.uvs is not None:
        first = mesh.materials[0]
        image = _tensor_to_image(first.texture, None) if first.texture is not None else None
        rgba = lambda colour: np.append(np.round(colour.detach().cpu().clamp(0, 1).numpy() * 255), 255).astype(np.uint8)  # noqa: E731
        material = trimesh.visual.material.SimpleMaterial(  # its colours, not trimesh's defaults (0.4 each)
            image=image, diffuse=rgba(first.diffuse), ambient=rgba(first.ambient), specular=rgba(first.specular),
            glossiness=float(first.shininess), name=first.name)
        visual = trimesh.visual.TextureVisuals(uv=mesh.uvs.detach().cpu().numpy(), material=material)
    return trimesh.Trimesh(vertices=mesh.positions.detach().cpu().numpy(), faces=mesh.faces.cpu().numpy(),
                           vertex_normals=mesh.normals.detach().cpu().numpy(), visual=visual, process=False)
