"""Pictures of decimated assets (a level of detail): the suite's own decimation (`decimate0.5`,
fast-simplification's quadric decimation of the mesh as stored, split at its UV seams) at 50 and 35 % of
the faces, and, with `--blender-python`, Blender's (the Decimate modifier, collapse, on the same mesh,
keeping UVs: `decimate_blenderR`), a level of detail made by another tool. Blender runs in its own
Python (an environment with `pip install bpy==5.0.1`), on arrays passed through a temporary .npz file.

    python experiments/decimation.py --data data --meshes 100 [--blender-python /tmp/venvb/bin/python]
        [--ratios 0.5 0.35] [--views 1]

(The reading with decimated copies of the original as candidates, measured and not taken, is commit
61528aa's: its `--decimations` and `--below` options; docs/reading.md, "Alternatives measured".)

Reads the first N test meshes as `meshseal eval --attacks none,decimate0.5,decimate0.35,decimate_blenderR`
does (seeded 256^2 views, marked as `meshseal embed` marks, camera known) and prints one line of JSON:
detected by attack and by kind of picture.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

BLENDER_SCRIPT = r"""
import sys, numpy as np, bpy
data = np.load(sys.argv[1]); ratio = float(sys.argv[3])
points, faces, loop_uv = data["points"], data["faces"], data["loop_uv"]
mesh = bpy.data.meshes.new("m")
mesh.from_pydata(points.tolist(), [], faces.tolist())
layer = mesh.uv_layers.new(name="uv")
layer.data.foreach_set("uv", loop_uv.reshape(-1))
mesh.update()
obj = bpy.data.objects.new("m", mesh)
bpy.context.scene.collection.objects.link(obj)
bpy.context.view_layer.objects.active = obj
modifier = obj.modifiers.new("decimate", "DECIMATE")
modifier.decimate_type = "COLLAPSE"; modifier.ratio = ratio; modifier.use_collapse_triangulate = True
depsgraph = bpy.context.evaluated_depsgraph_get()
result = obj.evaluated_get(depsgraph).to_mesh()
result.calc_loop_triangles()
out_points = np.array([v.co[:] for v in result.vertices], dtype=np.float64)
tris = [(t.vertices[:], t.loops[:]) for t in result.loop_triangles]
out_faces = np.array([v for v, _ in tris], dtype=np.int64).reshape(-1, 3)
uv = np.zeros(2 * len(result.loops)); result.uv_layers.active.data.foreach_get("uv", uv)
uv = uv.reshape(-1, 2)
out_uv = np.array([[uv[l] for l in loops] for _, loops in tris], dtype=np.float64).reshape(-1, 3, 2)
np.savez(sys.argv[2], points=out_points, faces=out_faces, corner_uv=out_uv)
"""


def blender_decimated(python: str, ratio: float):
    """An asset attack (Mesh, rng) -> Mesh: the mesh decimated by Blender to `ratio` of its faces, each
    output corner's UV as Blender interpolated it (a vertex on a UV seam split into one per UV), normals
    recomputed, one material (the first)."""
    import torch

    from meshseal.mesh import Mesh
    from meshseal.mesh.preprocess import vertex_normals

    def attack(mesh: Mesh, rng) -> Mesh:
        faces = mesh.faces.cpu().numpy()
        keep = faces[:, 0] != faces[:, 1]  # no padding faces ([0, 0, 0]) into Blender
        faces = faces[keep]
        uvs = mesh.uvs.cpu().double().numpy()
        with tempfile.TemporaryDirectory() as folder:
            given, made, script = Path(folder) / "in.npz", Path(folder) / "out.npz", Path(folder) / "run.py"
            np.savez(given, points=mesh.positions.cpu().double().numpy(), faces=faces, loop_uv=uvs[faces].reshape(-1, 2))
            script.write_text(BLENDER_SCRIPT)
            subprocess.run([python, str(script), str(given), str(made), str(ratio)], check=True,
                           capture_output=True)
            out = np.load(made)
            points, out_faces, corner_uv = out["points"], out["faces"], out["corner_uv"]
        # One output vertex per (position, UV) pair.
        keys = np.concatenate([out_faces.reshape(-1, 1).astype(np.float64), np.round(corner_uv.reshape(-1, 2), 7)], 1)
        unique, inverse = np.unique(keys, axis=0, return_inverse=True)
        positions = torch.from_numpy(points[unique[:, 0].astype(np.int64)]).to(mesh.positions.dtype)
        new_uvs = torch.from_numpy(unique[:, 1:]).to(mesh.uvs.dtype)
        new_faces = torch.from_numpy(inverse.reshape(-1, 3).astype(np.int64))
        normals = vertex_normals(positions, new_faces)
        return Mesh(positions, normals, new_faces, new_uvs, materials=mesh.materials[:1], up_axis=mesh.up_axis)
    return attack


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--blender-python", default=None, help="a Python with bpy: also Blender's decimation")
    parser.add_argument("--data", type=Path, default=ROOT / "data")
    parser.add_argument("--meshes", type=int, default=100)
    parser.add_argument("--ratios", type=float, nargs="+", default=[0.5, 0.35])
    parser.add_argument("--views", type=int, default=1)
    args = parser.parse_args()
    from meshseal.api import load as load_model
    from meshseal.data.dataset import MeshDataset
    from meshseal.evaluation import asset_attacks, attacks
    from meshseal.evaluation.evaluate import evaluate_registered

    asset_attacks.ASSET_ATTACKS.setdefault("decimate0.35", asset_attacks.decimated(0.35))
    attacks.ASSET_NAMES = (*attacks.ASSET_NAMES, "decimate0.35")
    names = ["decimate0.5", "decimate0.35"]
    for ratio in args.ratios if args.blender_python else []:
        name = f"decimate_blender{ratio:g}"
        asset_attacks.ASSET_ATTACKS[name] = blender_decimated(args.blender_python, ratio)
        attacks.ASSET_NAMES = (*attacks.ASSET_NAMES, name)
        names.append(name)
    model = load_model("default").model
    result = evaluate_registered(model, MeshDataset(args.data, "test", seed=0), args.meshes, 0, 256, "seed", None,
                                 views=args.views, register=False, max_flip=0.03, attacks=["none", *names])
    print(json.dumps({"attacks": result.get("attacks"), "by_kind": result.get("by_kind")}))


if __name__ == "__main__":
    main()
