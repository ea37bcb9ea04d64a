"""How often `meshseal detect` can say that the mesh given as the original is itself marked: test meshes
marked by `Watermarker.embed` under a key, each given back as its own original, its textures read alone
(`Method.own_mark_pvalue`) under that key. Prints, per model, how many read under the FPR and the median
log10 p-value; `--scales` sets the whitening windows of that reading (in cells; `methods.spread.OWN_MARK_SCALES`).

    python experiments/own_mark.py --data data --meshes 41 --models default,cell_pilot [--scales 0.5 1.0]
"""

from __future__ import annotations

import argparse

import numpy as np

import meshseal
from meshseal.data.dataset import MeshDataset
from meshseal.mesh import Material, Mesh
from meshseal.methods import spread
from meshseal.payload import FPR


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--meshes", type=int, default=41, help="about this many test meshes, every (284 // N)-th of the split")
    parser.add_argument("--models", default="default")
    parser.add_argument("--scales", type=float, nargs="+", default=None)
    args = parser.parse_args()
    if args.scales:
        spread.OWN_MARK_SCALES = tuple(args.scales)
    dataset = MeshDataset(args.data, "test", seed=0)
    models = {name: meshseal.load(name) for name in args.models.split(",")}
    p_values = {name: [] for name in models}
    for index in range(0, len(dataset), max(1, len(dataset) // args.meshes)):
        item = dataset[index]
        n_verts, n_faces = int(item["n_verts"]), int(item["n_faces"])
        mesh = Mesh(item["positions"][:n_verts], item["normals"][:n_verts], item["faces"][:n_faces],
                    item["uvs"][:n_verts], materials=[Material(texture=item["texture"].permute(1, 2, 0))])
        for name, watermarker in models.items():
            marked = watermarker.embed(mesh, "ab42", key="s3cret", warn=False)
            p_values[name].append(watermarker.method.own_mark_pvalue(watermarker.original(marked), "s3cret"))
    print(f"whitening windows {spread.OWN_MARK_SCALES} cells")
    for name, values in p_values.items():
        values = np.maximum(np.array(values, dtype=float), 1e-300)
        print(f"{name}: {len(values)} meshes, own mark read under the FPR on {int((values <= FPR).sum())}, "
              f"median p 1e{np.median(np.log10(values)):.0f}")


if __name__ == "__main__":
    main()
