"""How many test meshes each spread model marks on each of its cell grids, and how many detection reads
on two grids (a mesh near a threshold): `python experiments/grid_counts.py --data data --models default fine`."""

from __future__ import annotations

import argparse
import collections

from meshseal.api import load
from meshseal.data.dataset import MeshDataset, collate
from meshseal.threads import configure


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--models", nargs="+", default=["default", "fine"])
    args = parser.parse_args()
    configure()
    dataset = MeshDataset(args.data, "test")
    for name in args.models:
        encoder = load(name, "cpu").model.texture_encoder
        grids, both = collections.Counter(), 0
        for index in range(len(dataset)):
            batch = collate([dataset[index]], "cpu")
            geometry = batch["positions"][0], batch["faces"][0], batch["uvs"][0]
            grids[encoder.grid_for(*geometry)] += 1
            both += len(encoder.grids_to_read(*geometry)) > 1
        cells = ", ".join(f"{count} on {grid}^2" for grid, count in sorted(grids.items()))
        print(f"{name}: {len(dataset)} test meshes: marked {cells}; read on two grids: {both}")


if __name__ == "__main__":
    main()
