"""Which colour and cell size survive JPEG: the spread mark's colour direction and cell grid against
what JPEG keeps (full-resolution luminance, chroma subsampled 4:2:0 and quantised harder).

For each colour x chips (the model's other settings unchanged, texture PSNR 40 dB at strength 1): the
mark's visibility on the bunny, Suzanne and teapot fixtures (object-pixel PSNR and FLIP between original
and marked renders, 2 seeded views, 256^2; the teapot's, the worst, also alone), and bit accuracy with the camera known on test meshes
START, START+STRIDE, ... (one seeded 256^2 view each, `experiments/footprint.py`'s pictures) as saved
(PNG) and re-saved as JPEG at quality 75 and 90 (Pillow's defaults: 4:2:0). A colour is a name of
`models.spread.COLOURS` or `mix:F`: the mark's energy split between grey (a share F) and blue-yellow,
two orthogonal directions.

    python experiments/mark_colour.py --data data [--meshes 20] [--stride 2] [--colours grey blue-yellow mix:0.5]
        [--chips 128 64]
"""

from __future__ import annotations

import argparse
import copy
import io
from pathlib import Path

import numpy as np
import torch
from footprint import pictures
from PIL import Image

import meshseal
from meshseal import payload
from meshseal.data.dataset import MeshDataset
from meshseal.mesh import load, normalize, to_z_up
from meshseal.evaluation.metrics import visibility
from meshseal.models.spread import COLOURS, SpreadSpectrumEncoder, soft_bits
from meshseal.render.views import sample_views
from meshseal.methods.spread import spread_evidence
from meshseal.render import MeshBatch, MeshRenderer

FIXTURES = Path(__file__).resolve().parents[1] / "tests" / "fixtures"


def jpeg(picture: torch.Tensor, quality: int) -> torch.Tensor:
    """(1, 3, H, W) in [0, 1] -> the same picture after a JPEG round trip at `quality`."""
    array = (picture[0].permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="JPEG", quality=quality)
    buffer.seek(0)
    return torch.from_numpy(np.array(Image.open(buffer))).permute(2, 0, 1)[None].float() / 255


def fixture_visibility(encoder: SpreadSpectrumEncoder) -> dict:
    rows = []
    for name in ("bunny.glb", "suzanne.glb", "teapot/teapot.obj"):
        mesh = normalize(to_z_up(load(FIXTURES / name)))
        texture = mesh.materials[0].texture.permute(2, 0, 1)[None]
        message = torch.randint(0, 2, (1, encoder.n_bits), generator=torch.Generator().manual_seed(3)).float()
        original, marked = MeshBatch.from_mesh(mesh), MeshBatch.from_mesh(mesh)
        marked.textures = [encoder(texture, message)[0]]
        cameras, lights = sample_views(2, "seed", torch.Generator().manual_seed(0))
        seen, expected = (MeshRenderer()(m, cameras, lights, 256, 256) for m in (original, marked))
        rows.append(visibility(seen.image, expected.image, seen.rgba[..., 3] > 0.999))
    return {**{key: float(np.mean([row[key] for row in rows])) for key in ("psnr_object", "flip_object")},
            "teapot": rows[-1]}


def mark_encoder(shipped: SpreadSpectrumEncoder, colour: str, chips: int) -> SpreadSpectrumEncoder:
    """The shipped encoder with another colour direction and cell grid."""
    e = shipped
    if not colour.startswith("mix:"):
        return SpreadSpectrumEncoder(e.n_bits, chips, colour, e.texture_psnr, e.window, e.floor, e.seed)
    encoder = SpreadSpectrumEncoder(e.n_bits, chips, "grey", e.texture_psnr, e.window, e.floor, e.seed)
    share = float(colour[4:])
    grey, blue_yellow = (torch.nn.functional.normalize(torch.tensor(COLOURS[c]), dim=0) for c in ("grey", "blue-yellow"))
    encoder.colour = share ** 0.5 * grey + (1 - share) ** 0.5 * blue_yellow
    return encoder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--meshes", type=int, default=20)
    parser.add_argument("--stride", type=int, default=2)
    parser.add_argument("--colours", nargs="+", default=["blue-yellow", "grey"])
    parser.add_argument("--chips", nargs="+", type=int, default=[128, 64])
    args = parser.parse_args()
    shipped = meshseal.load().model
    dataset = MeshDataset(args.data, "test")
    public = payload.key_seed(None)
    print("| colour | chips | object PSNR | object FLIP | teapot PSNR / FLIP | PNG | JPEG 90 | JPEG 75 |\n"
          "|---|---|---|---|---|---|---|---|")
    for colour in args.colours:
        for chips in args.chips:
            model = copy.deepcopy(shipped)
            model.texture_encoder = mark_encoder(shipped.texture_encoder, colour, chips)
            accuracy = {"PNG": [], "JPEG 90": [], "JPEG 75": []}
            with torch.no_grad():
                seen = fixture_visibility(model.texture_encoder)
                for index in range(args.start, args.start + args.meshes * args.stride, args.stride):
                    original, cameras, message, shots = pictures(model, dataset, index)
                    for name, picture in (("PNG", shots["point"]), ("JPEG 90", jpeg(shots["point"], 90)),
                                          ("JPEG 75", jpeg(shots["point"], 75))):
                        z = soft_bits(model.texture_encoder, spread_evidence(model, original, picture, cameras), public)[0]
                        accuracy[name].append(float(((z > 0).double() == message).double().mean()))
            teapot = seen["teapot"]
            print(f"| {colour} | {chips} | {seen['psnr_object']:.2f} | {seen['flip_object']:.4f} | "
                  f"{teapot['psnr_object']:.2f} / {teapot['flip_object']:.4f} | "
                  + " | ".join(f"{np.mean(v):.4f}" for v in accuracy.values()) + " |", flush=True)


if __name__ == "__main__":
    main()
