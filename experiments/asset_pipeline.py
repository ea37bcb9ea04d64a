"""The asset's road: what an engine import or a re-export does to a marked mesh, then one picture read.

Each mesh (the textured fixtures, and the first N test meshes of --data) is marked as `meshseal embed`
marks it (within the FLIP budget) by each model, then put through one asset-pipeline step at a time:
its textures re-saved as JPEG 90 (Pillow, 4:2:0), halved (bicubic), block-compressed as BC1 or BC7
(`etcpak` to encode, `texture2ddecoder` to decode), the mesh saved as OBJ and converted to GLB through
trimesh and read back (`obj_glb`), or decimated to half its faces keeping its UVs (`mesh.simplify`).
The result is rendered by our renderer from one seeded view (256^2, 8-bit) and read against the
unmarked original with the camera known. Reports detected / exact message / named at FPR 1e-6 per step
(named: the owner's test of the message it embedded, `detect --expect-id`, on the same reading), by kind
of asset (fixtures with their own textures; test meshes, whose textures the dataset stores at 128^2).

    pip install etcpak texture2ddecoder
    python experiments/asset_pipeline.py --data data --meshes 40 [--models default robust]
"""

from __future__ import annotations

import argparse
import io
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from PIL import Image

import meshseal
from meshseal.data.dataset import MeshDataset
from meshseal.mesh import normalize, simplify, to_z_up
from meshseal.render import MeshBatch, MeshRenderer
from meshseal.render.views import sample_views
from meshseal.training.finetune import mesh_from_item

FIXTURES = Path(__file__).resolve().parents[1] / "tests" / "fixtures"
FIXTURE_FILES = ["bunny.glb", "suzanne.glb", "multi_material.glb", "teapot/teapot.obj", "sh3d_crate/crate.obj",
                 "sh3d_deckChair/deckChair.obj"]
STEPS = ["none", "jpeg90", "half", "bc1", "bc7", "obj_glb", "decimate"]


def _textures(mesh, change):
    out = mesh.copy()
    for material in out.materials:
        if material.texture is not None:
            pixels = (material.texture.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
            material.texture = torch.from_numpy(change(pixels).astype(np.float32) / 255.0)
    return out


def _jpeg(pixels):
    buffer = io.BytesIO()
    Image.fromarray(pixels).save(buffer, format="JPEG", quality=90)
    return np.asarray(Image.open(io.BytesIO(buffer.getvalue())).convert("RGB"))


def _half(pixels):
    height, width = pixels.shape[:2]
    return np.asarray(Image.fromarray(pixels).resize((max(1, width // 2), max(1, height // 2)), Image.BICUBIC))


def _block(kind):
    import etcpak
    import texture2ddecoder

    def change(pixels):
        height, width = pixels.shape[:2]
        padded = np.pad(pixels, ((0, -height % 4), (0, -width % 4), (0, 0)), mode="edge")
        rgba = np.concatenate([padded, np.full(padded.shape[:2] + (1,), 255, np.uint8)], axis=2)
        h, w = rgba.shape[:2]
        if kind == "bc1":
            data = etcpak.compress_bc1(rgba.tobytes(), w, h)
            decoded = texture2ddecoder.decode_bc1(data, w, h)
        else:
            data = etcpak.compress_bc7(rgba.tobytes(), w, h, None)
            decoded = texture2ddecoder.decode_bc7(data, w, h)
        bgra = np.frombuffer(decoded, np.uint8).reshape(h, w, 4)
        return np.ascontiguousarray(bgra[:height, :width, [2, 1, 0]])
    return change


def _obj_glb(mesh):
    """Saved in its own format (GLB for a mesh made in memory), converted by trimesh to the other one
    (OBJ <-> GLB) and read back."""
    import trimesh

    suffix = mesh.source.path.suffix.lower() if mesh.source is not None else ".glb"
    other = ".obj" if suffix == ".glb" else ".glb"
    with tempfile.TemporaryDirectory() as folder:
        meshseal.save_mesh(mesh, Path(folder) / f"a{suffix}")
        trimesh.load(Path(folder) / f"a{suffix}", force="scene").export(Path(folder) / f"b{other}")
        converted = meshseal.load_mesh(Path(folder) / f"b{other}")
    # a mesh made in memory is in the canonical Z-up frame, which a GLB file does not say: keep it
    return converted if mesh.source is not None else replace(converted, up_axis=mesh.up_axis)


def step(mesh, name):
    if name == "none":
        return mesh
    if name == "jpeg90":
        return _textures(mesh, _jpeg)
    if name == "half":
        return _textures(mesh, _half)
    if name in ("bc1", "bc7"):
        return _textures(mesh, _block(name))
    if name == "obj_glb":
        return _obj_glb(mesh)
    if name == "decimate":
        return simplify(mesh, max(4, mesh.n_faces // 2))
    raise ValueError(name)


def _picture(mesh, cameras, lights) -> np.ndarray:
    canonical = normalize(to_z_up(replace(mesh, source=None)))
    with torch.no_grad():
        image = MeshRenderer()(MeshBatch.from_mesh(canonical), cameras, lights, 256, 256, (0.5, 0.5, 0.5)).image
    return (image[0].clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None)
    parser.add_argument("--meshes", type=int, default=40)
    parser.add_argument("--models", nargs="+", default=["default", "chroma", "robust"])
    args = parser.parse_args()
    assets = [("fixture", meshseal.load_mesh(FIXTURES / name)) for name in FIXTURE_FILES]
    if args.data is not None:
        dataset = MeshDataset(args.data, "test", seed=0)
        assets += [("test mesh", mesh_from_item(dataset[i])) for i in range(min(args.meshes, len(dataset)))]
    print("| model | assets | " + " | ".join(STEPS) + " |")
    print("|---|---|" + "---|" * len(STEPS))
    for name in args.models:
        watermarker = meshseal.load(name, "cpu")
        counts = {}
        for index, (kind, mesh) in enumerate(assets):
            generator = torch.Generator().manual_seed(index)
            message = int(torch.randint(0, 2 ** 31, (1,), generator=generator))
            marked, _ = watermarker.embed_within(mesh, message)
            original = watermarker.original(mesh)
            cameras, lights = sample_views(1, "seed", generator)
            for what in STEPS:
                tally = counts.setdefault((kind, what), [0, 0, 0, 0])
                tally[0] += 1
                try:
                    picture = _picture(step(marked, what), cameras, lights)
                    reading = watermarker.read(picture, original, camera=cameras)
                except meshseal.MeshsealError:
                    continue
                result = watermarker.decide([reading])
                tally[1] += bool(result.detected)
                tally[2] += result.message == message
                tally[3] += bool(watermarker.decide([reading], expect=message).detected)
        for kind in ("fixture", "test mesh"):
            if (kind, "none") in counts:
                cells = " | ".join(" / ".join(f"{counts[(kind, s)][i] / counts[(kind, s)][0]:.2f}" for i in (1, 2, 3))
                                   for s in STEPS)
                print(f"| {name} | {counts[(kind, 'none')][0]} {'test meshes' if kind == 'test mesh' else kind + 's'} | {cells} |", flush=True)


if __name__ == "__main__":
    main()
