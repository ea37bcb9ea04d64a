"""The strength knob: what `meshseal embed --strength S` costs in visibility and buys in robustness.

For each textured fixture and strength: embed a text message with the shipped model (public key),
measure texture PSNR (over the texels the mesh shows, which the knob sets, and the whole texture) and, over the object's pixels in 256^2 renders, PSNR and FLIP (the same figures
`meshseal embed` prints), then read K seeded views with the camera known, as saved (PNG), after JPEG
75 and at half size, and report the detection rate at FPR 1e-6, the exact-message rate and the mean
signed z of the bits (the margin the decision has).

    python experiments/strength_sweep.py [--strengths 0.5 1 2 4] [--views 2] [--fixtures bunny teapot crate]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

import meshseal
from meshseal import payload
from meshseal.evaluation.reports import embed_report
from meshseal.mesh import normalize, to_z_up
from meshseal.methods import read_bits
from meshseal.render.views import sample_views
from meshseal.render import MeshBatch, MeshRenderer

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from calibrate import quantise, variants  # noqa: E402

FIXTURES = Path(__file__).resolve().parents[1] / "tests" / "fixtures"
TEXTURED = {"bunny": "bunny.glb", "teapot": "teapot/teapot.obj", "crate": "sh3d_crate/crate.obj",
            "deckChair": "sh3d_deckChair/deckChair.obj", "suzanne": "suzanne.glb", "multi_material": "multi_material.glb"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--strengths", type=float, nargs="+", default=[0.5, 1.0, 2.0, 4.0])
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--fixtures", nargs="+", default=["bunny", "teapot", "crate"])
    parser.add_argument("--model", default="default", help="shipped model name or .safetensors path")
    args = parser.parse_args()
    wm = meshseal.load(args.model)
    key_seed = payload.key_seed(None)
    expected = payload.encode("ab42", None, wm.n_bits)
    print("| strength | texture PSNR, shown texels | texture PSNR | object PSNR | object FLIP | " + " | ".join(
        f"{v}: detected / exact / z" for v in ("png", "jpeg75", "half size")) + " |")
    print("|---" * 8 + "|")
    for strength in args.strengths:
        visibility, reads = [], {}
        for name in args.fixtures:
            mesh = meshseal.load_mesh(FIXTURES / TEXTURED[name])
            marked = wm.embed(mesh, "ab42", strength=strength)
            report, _ = embed_report(mesh, marked, args.views)
            visibility.append((report["psnr_texture_shown"], report["psnr_texture"], report["psnr_object"],
                               report["flip_object"]))
            original = wm.original(mesh)
            batch = MeshBatch.from_mesh(normalize(to_z_up(marked)))
            cameras, lights = sample_views(args.views, "seed", torch.Generator().manual_seed(args.seed))
            with torch.no_grad():
                pictures = quantise(MeshRenderer()(batch, cameras, lights, 256, 256).image)
                for label, images in variants(pictures, torch.Generator().manual_seed(args.seed), attacks=False).items():
                    for z in read_bits(wm.model, original, images, cameras, key_seed).double():
                        decided = payload.detected(payload.detection_pvalue(z))
                        exact = payload.decode(z).message == "ab42"
                        reads.setdefault(label, []).append((decided, decided and exact,
                                                            float((z * (2 * expected - 1)).mean())))
        mean = np.mean(visibility, axis=0)
        cells = [f"{np.mean([r[0] for r in rows]):.2f} / {np.mean([r[1] for r in rows]):.2f} / "
                 f"{np.mean([r[2] for r in rows]):.2f}" for rows in reads.values()]
        print(f"| {strength:g} | {mean[0]:.2f} | {mean[1]:.2f} | {mean[2]:.2f} | {mean[3]:.4f} | " + " | ".join(cells) + " |",
              flush=True)


if __name__ == "__main__":
    main()
