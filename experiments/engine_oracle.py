"""Is the mark lost in an engine's pictures, or is the prediction wrong? The shipped matched filter with
the true camera against the same filter given the engine's own render of the original as its
prediction (an oracle no user has: the same engine, view, light and sampling noise, without the mark).

Per fixture and engine (2 seeded views, 256^2, grey background, 8-bit pictures): bit accuracy as
shipped and with the oracle prediction, and the RMS along the mark's colour of picture minus
prediction over the object's pixels (the mark alone: the oracle's figure).

    python experiments/engine_oracle.py [--engines ours cycles eevee workbench] [--meshes deckChair bunny]
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np
import torch
from engines import BACKGROUND, FIXTURES, TEXTURED

import meshseal
from meshseal import payload, pipeline
from meshseal.mesh import normalize, to_z_up
from meshseal.models.spread import soft_bits
from meshseal.render.views import sample_views
from meshseal.methods.spread import spread_evidence
from meshseal.render import make_renderer, pixels_at


def read(wm, original, picture, camera, prediction=None):
    """(z (N,), along-colour residual RMS) of the shipped filter; `prediction` (1, 3, H, W) replaces
    the relit original."""
    relit, seen = pipeline.relit_residual, []

    def patched(mesh, image, cameras, light_from="all"):
        found = relit(mesh, image, cameras, light_from)
        if prediction is not None:
            found = replace(found, expected=pixels_at(prediction, found.fragments).index_select(0, found.keep))
        seen.append(found)
        return found

    pipeline.relit_residual = patched
    try:
        evidence = spread_evidence(wm.model, original, picture, camera, footprint=prediction is None)
    finally:
        pipeline.relit_residual = relit
    rms = float(((seen[0].seen - seen[0].expected) @ wm.model.texture_encoder.colour).std())
    return soft_bits(wm.model.texture_encoder, evidence, payload.key_seed(None))[0], rms


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--engines", nargs="+", default=["ours", "cycles", "eevee", "workbench"])
    parser.add_argument("--meshes", nargs="+", default=list(TEXTURED))
    parser.add_argument("--views", type=int, default=2)
    args = parser.parse_args()
    wm = meshseal.load()
    print("| mesh | engine | bit acc. (shipped) | bit acc. (oracle prediction) | residual RMS (shipped) | "
          "residual RMS (oracle: the mark) |\n|---|---|---|---|---|---|")
    for index, name in enumerate(args.meshes):
        mesh = meshseal.load_mesh(FIXTURES / TEXTURED[name])
        message = f"{index:04d}"
        marked = wm.embed(mesh, message)
        expected = payload.encode(message, None, wm.n_bits).numpy()
        canonical = [normalize(to_z_up(replace(m, source=None))) for m in (mesh, marked)]
        original = wm.original(mesh)
        cameras, lights = sample_views(args.views, "seed", torch.Generator().manual_seed(index))
        for engine in args.engines:
            renderer = make_renderer(engine)
            with torch.no_grad():
                plain, carrying = (torch.round(renderer.render(m, cameras, lights, 256, 256, background=BACKGROUND)
                                               [..., :3].clamp(0, 1).permute(0, 3, 1, 2) * 255) / 255 for m in canonical)
                rows = []
                for view in range(args.views):
                    camera = cameras[[view]]
                    shipped, rms = read(wm, original, carrying[[view]], camera)
                    oracle, mark = read(wm, original, carrying[[view]], camera, plain[[view]])
                    rows.append([float(((z > 0).numpy() == expected).mean()) for z in (shipped, oracle)] + [rms, mark])
            acc, acc_oracle, rms, mark = np.mean(rows, 0)
            print(f"| {name} | {engine} | {acc:.3f} | {acc_oracle:.3f} | {rms * 255:.2f} | {mark * 255:.2f} |", flush=True)


if __name__ == "__main__":
    main()
