"""`meshseal info`: what a mesh file contains (counts, materials, textures, UVs, up axis, bounds)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ._common import require_mesh


def register(subparsers) -> None:
    parser = subparsers.add_parser("info", help="describe a mesh file",
                                   description="Print the vertex/face counts, parts, materials and "
                                               "textures, UVs, normals, up axis and bounds of a mesh file.")
    parser.add_argument("mesh", type=Path, help="mesh file (.obj, .glb, .gltf, .ply, .off, .stl)")
    parser.add_argument("--up", choices=("y", "z"), default=None, help="override the file's up axis")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.set_defaults(func=run)


def describe(mesh, path: Path) -> dict:
    """A JSON-ready description of a loaded mesh (bounds in the file's own frame)."""
    import torch

    source = mesh.source
    face_counts = torch.bincount(mesh.face_material, minlength=len(mesh.materials)).tolist()
    materials = []
    for material, n_faces in zip(mesh.materials, face_counts):
        texture = None
        if material.texture is not None:
            height, width = material.texture.shape[:2]
            texture = {"width": int(width), "height": int(height)}
        materials.append({"name": material.name, "texture": texture, "faces": int(n_faces),
                          "diffuse": [round(float(v), 4) for v in material.diffuse]})
    low, high = mesh.positions.min(dim=0).values, mesh.positions.max(dim=0).values
    normal_length = mesh.normals.norm(dim=-1)
    return {
        "path": str(path),
        "format": source.file_type if source is not None else path.suffix.lstrip(".").lower(),
        "vertices": mesh.n_vertices,
        "faces": mesh.n_faces,
        "parts": [{"node": p.node, "geometry": p.geometry, "vertices": p.vertices.stop - p.vertices.start,
                   "faces": p.faces.stop - p.faces.start} for p in (source.parts if source else [])],
        "materials": materials,
        "uvs": mesh.uvs is not None,
        "normals": bool(((normal_length - 1).abs() < 1e-3).all()),
        "up_axis": mesh.up_axis,
        "bounds": {"min": [float(v) for v in low], "max": [float(v) for v in high]},
    }


def _text(info: dict) -> str:
    def vec(values):
        return "(" + ", ".join(f"{v:.4g}" for v in values) + ")"

    lines = [f"{info['path']} ({info['format'].upper()})",
             f"  vertices:  {info['vertices']}",
             f"  faces:     {info['faces']}",
             f"  parts:     {len(info['parts'])}"
             + (": " + ", ".join(p["node"] for p in info["parts"]) if info["parts"] else ""),
             f"  materials: {len(info['materials'])}"]
    for material in info["materials"]:
        texture = material["texture"]
        size = f"texture {texture['width']}x{texture['height']}" if texture else "no texture"
        lines.append(f"    - {material['name']}: {size}, {material['faces']} faces")
    lines += [f"  uvs:       {'yes' if info['uvs'] else 'no'}",
              f"  normals:   {'yes' if info['normals'] else 'no (degenerate)'}",
              f"  up axis:   {info['up_axis']}",
              f"  bounds:    min {vec(info['bounds']['min'])}  max {vec(info['bounds']['max'])}"]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    require_mesh(args.mesh)
    from ..mesh import load

    info = describe(load(args.mesh, up_axis=args.up), args.mesh)
    print(json.dumps(info) if args.json else _text(info))
    return 0
