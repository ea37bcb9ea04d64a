"""`reading.imports.pick_normals` (the shading change of the recomputed normals added to the prediction)
against the decision it replaced (the original rendered again with those normals), picture by picture.

The first N test meshes of --data are marked by the default model (message: the mesh's index as 4
digits), shown as marked and converted OBJ <-> GLB (`obj_glb`: trimesh recomputes the normals), rendered
by our renderer from one seeded view of the seed's ranges at 256^2 over grey, and read against the
original. Where the original has a normals candidate (`reading.imports.imported`), both decisions are
taken on the same relit residual; the run prints the pictures where they differ, how many each picked and
the milliseconds each took.

    python experiments/normals_pick.py --data data --meshes 80
    python experiments/normals_pick.py --data data --meshes 60 --picture-log obj_glb

`--picture-log ATTACKS` takes both decisions inside `experiments/picture_log.py`'s reading instead (its
pictures: full strength, its views and backgrounds; the shading change's decision is the one used) and
counts the calls where they differ.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

import meshseal
from meshseal.data.dataset import MeshDataset
from meshseal.evaluation.asset_attacks import apply as asset_apply
from meshseal.mesh import normalize, to_z_up
from meshseal.reading import imports
from meshseal.reading.relight import relit_residual
from meshseal.render import MeshBatch, MeshRenderer, pixels_at
from meshseal.render.views import sample_views
from meshseal.training.finetune import mesh_from_item


def rendered_decision(found, normals: torch.Tensor, cameras, shape: tuple[int, int, int]) -> bool:
    """The decision as it was made before: the original rendered again with `normals` under the fitted
    light, the high-passed residuals compared (under PICK_BELOW of the given normals')."""
    _, height, width = shape
    other = MeshRenderer()(replace(found.relit, normals=normals), cameras, found.lights, height, width,
                           fragments=found.fragments)
    expected = pixels_at(other.image, found.fragments).index_select(0, found.keep).to(found.seen)
    pixel = found.fragments.pixel.index_select(0, found.keep)
    given = imports._detail(found.seen - found.expected, pixel, shape)
    return imports._detail(found.seen - expected, pixel, shape) < imports.PICK_BELOW * given


def through_picture_log(data: Path, meshes: int, attacks: str) -> None:
    """Both decisions on every call `experiments/picture_log.py` makes, the shading change's used."""
    import runpy
    import sys
    import tempfile

    shading = imports.pick_normals
    calls = {"made": 0, "differ": 0}

    def both(found, normals, cameras, shape):
        rendered, used = rendered_decision(found, normals, cameras, shape), shading(found, normals, cameras, shape)
        calls["made"] += 1
        if rendered != used:
            calls["differ"] += 1
            print(f"call {calls['made']}: rendered {rendered}, shading change {used} ({len(found.keep)} pixels)", flush=True)
        return used

    imports.pick_normals = both
    with tempfile.TemporaryDirectory() as folder:
        sys.argv = ["picture_log.py", "--data", str(data), "--meshes", str(meshes), "--attacks", attacks,
                    "--out", str(Path(folder) / "log.jsonl")]
        runpy.run_path(str(Path(__file__).with_name("picture_log.py")), run_name="__main__")
    print(f"{calls['made']} normals decisions in picture_log's reading (first {meshes} test meshes, PNG and {attacks}): "
          f"{calls['differ']} differ")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--meshes", type=int, default=80)
    parser.add_argument("--picture-log", metavar="ATTACKS", help="take both decisions in picture_log.py's reading")
    args = parser.parse_args()
    if args.picture_log:
        through_picture_log(args.data, args.meshes, args.picture_log)
        return
    wm = meshseal.load("default", "cpu")
    dataset = MeshDataset(args.data, "test", seed=0)
    shape = (1, 256, 256)
    agree = total = 0
    picked = [0, 0]
    seconds = [0.0, 0.0]
    for index in range(min(args.meshes, len(dataset))):
        mesh = mesh_from_item(dataset[index])
        original = wm.original(mesh)
        candidate = wm.method.imports_of(original)
        if candidate is None or candidate.normals is None:
            continue
        marked = wm.embed(mesh, f"{index:04d}")
        cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(index))
        for attack in ("none", "obj_glb"):
            shown = marked if attack == "none" else asset_apply(attack, marked, np.random.default_rng([index, 7]))
            with torch.no_grad():
                image = MeshRenderer()(MeshBatch.from_mesh(normalize(to_z_up(replace(shown, source=None)))), cameras,
                                       lights, 256, 256, (0.5, 0.5, 0.5)).image
                image = (image.clamp(0, 1) * 255).round() / 255
                found = relit_residual(original, image, cameras)
                decisions = []
                for slot, decide in enumerate((rendered_decision, imports.pick_normals)):
                    started = time.perf_counter()
                    decisions.append(bool(decide(found, candidate.normals, cameras, shape)))
                    seconds[slot] += time.perf_counter() - started
            total += 1
            agree += decisions[0] == decisions[1]
            picked = [p + d for p, d in zip(picked, decisions)]
            if decisions[0] != decisions[1]:
                print(f"mesh {index} ({attack}): rendered {decisions[0]}, shading change {decisions[1]}", flush=True)
    print(f"{total} pictures with a normals candidate (first {args.meshes} test meshes, as marked and OBJ <-> GLB): "
          f"the same decision on {agree}; picked by the render {picked[0]}, by the shading change {picked[1]}; "
          f"ms a decision {1000 * seconds[0] / max(total, 1):.1f} / {1000 * seconds[1] / max(total, 1):.1f}")


if __name__ == "__main__":
    main()
