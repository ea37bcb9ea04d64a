"""xatlas unwraps in a child process.

xatlas runs a thread pool inside each atlas and joins it when the atlas is destroyed; that join can
wait forever (a worker that missed its wake-up: seen once in some thousand atlases, in `meshseal eval`
on the test split). The child makes every atlas a batch asks for, writes the results and leaves with
`os._exit`, so no atlas is ever destroyed; the parent waits at most `TIMEOUT` seconds a try and tries
`TRIES` times. The child runs this file as a script (not the package, whose import costs seconds) and
imports numpy and xatlas only.

    python -I src/meshseal/methods/unwrap.py < jobs.npz > results.npz   (what `unwrap_many` runs)
"""

from __future__ import annotations

import io
import os
import subprocess
import sys

import numpy as np

TIMEOUT = 300.0  # seconds a try
TRIES = 2


def unwrap_many(jobs: list[tuple[np.ndarray, np.ndarray, float]]) -> list[tuple[tuple[int, int], np.ndarray, np.ndarray, np.ndarray]]:
    """Each job (vertices (V, 3) float64, faces (F, 3) uint32, texels per unit length) unwrapped by
    xatlas (padding 1, bilinear): ((height, width), vertex sources (V',) int64, faces (F', 3) int64,
    texel positions (V', 2), x right, y down), in the jobs' order."""
    from ..errors import MeshsealError

    if not jobs:
        return []
    buffer = io.BytesIO()
    arrays = {}
    for index, (vertices, faces, density) in enumerate(jobs):
        arrays |= {f"v{index}": np.asarray(vertices, np.float64), f"f{index}": np.asarray(faces, np.uint32),
                   f"d{index}": np.float64(density)}
    np.savez(buffer, count=np.int64(len(jobs)), **arrays)
    for _ in range(TRIES):
        try:
            done = subprocess.run([sys.executable, "-I", __file__], input=buffer.getvalue(),
                                  capture_output=True, timeout=TIMEOUT, check=False)
        except subprocess.TimeoutExpired:
            continue
        if done.returncode == 0:
            with np.load(io.BytesIO(done.stdout)) as out:
                return [((int(out[f"h{i}"]), int(out[f"w{i}"])), out[f"s{i}"], out[f"i{i}"], out[f"t{i}"])
                        for i in range(len(jobs))]
        raise MeshsealError(f"xatlas could not unwrap the palette faces: {done.stderr.decode(errors='replace').strip()[-300:]}")
    raise MeshsealError(f"xatlas did not finish unwrapping the palette faces in {TRIES} tries of {TIMEOUT:g} s")


def _child() -> None:
    import xatlas

    with np.load(io.BytesIO(sys.stdin.buffer.read())) as jobs:
        kept, out = [], {}
        for i in range(int(jobs["count"])):
            atlas = xatlas.Atlas()
            atlas.add_mesh(jobs[f"v{i}"], jobs[f"f{i}"])
            options = xatlas.PackOptions()
            options.padding, options.texels_per_unit, options.bilinear = 1, float(jobs[f"d{i}"]), True
            atlas.generate(xatlas.ChartOptions(), options)
            sources, indices, uvs = atlas[0]
            texels = np.stack([uvs[:, 0] * atlas.width, (1 - uvs[:, 1]) * atlas.height], 1)
            out |= {f"h{i}": np.int64(atlas.height), f"w{i}": np.int64(atlas.width), f"s{i}": sources.astype(np.int64),
                    f"i{i}": indices.astype(np.int64), f"t{i}": texels}
            kept.append(atlas)  # never destroyed: see the module docstring
    buffer = io.BytesIO()
    np.savez(buffer, **out)
    sys.stdout.buffer.write(buffer.getvalue())
    sys.stdout.buffer.flush()
    os._exit(0)


if __name__ == "__main__":
    _child()
