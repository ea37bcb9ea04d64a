"""A second, luminance layer for JPEG: the shipped blue-yellow mark plus an independent grey one.

JPEG keeps full-resolution luminance and drops fine chroma (4:2:0), so the shipped blue-yellow mark
is gone from any JPEG, while a grey mark survives part of it (docs/invisibility.md). Here the mark's
energy is split: a share F on a grey layer with its own keyed cells (`--grey-chips` per side), the
rest on the shipped blue-yellow layer, the texture PSNR unchanged. Each layer is read by its own
matched filter; their per-bit z are combined with fixed weights (a sum of Rademacher sums: the
exact null stays). Reports, per share: visibility on the bunny, Suzanne and teapot (object PSNR and
FLIP), and on test meshes (one seeded 256^2 view each, camera known) bit accuracy and detection at
FPR 1e-6 for each layer alone and combined, as PNG and as JPEG 90 / 75.

    python experiments/jpeg_layers.py --data data [--meshes 12] [--stride 8] [--shares 0 0.3 0.5]
"""

from __future__ import annotations

import argparse
import copy
from dataclasses import replace

import numpy as np
import torch
from engines import item_mesh
from mark_colour import fixture_visibility, jpeg

import meshseal
from meshseal import payload
from meshseal.data.dataset import MeshDataset
from meshseal.models.spread import SpreadSpectrumEncoder, bit_weights, soft_bits
from meshseal.mesh import normalize, to_z_up
from meshseal.render.views import sample_views
from meshseal.methods.spread import spread_evidence
from meshseal.render import make_renderer


class TwoLayers(torch.nn.Module):
    """The shipped encoder's mark at energy share 1 - F plus a grey one at share F (own cells)."""

    def __init__(self, chroma: SpreadSpectrumEncoder, grey: SpreadSpectrumEncoder, share: float, strength: float = 1.0):
        super().__init__()
        self.chroma, self.grey, self.share, self.strength = chroma, grey, share, strength
        self.n_bits = chroma.n_bits

    def forward(self, texture, message, strength=None, key_seed=None):
        strength = self.strength if strength is None else strength
        out = texture
        for encoder, part in ((self.chroma, 1 - self.share), (self.grey, self.share)):
            if part > 0:
                out = out + encoder(texture, message, strength * part ** 0.5, key_seed) - texture
        return out.clamp(0, 1)


def read(readers, original, picture, cameras, key, brightness_grey, grey_whitening=None):
    """Per layer: z (N,) and bit weights (N, M)."""
    out = {}
    for name, reader in readers.items():
        encoder = reader.texture_encoder
        brightness = name == "chroma" or brightness_grey
        whitening = grey_whitening if name == "grey" else None
        evidence = spread_evidence(reader, original, picture, cameras, whitening=whitening, brightness=brightness)
        out[name] = (soft_bits(encoder, evidence, key)[0].double(), bit_weights(encoder, evidence, key)[0].double())
    return out


def combine(parts, weights):
    z = sum(w * parts[name][0] for name, w in weights.items()) / np.sqrt(sum(w * w for w in weights.values()))
    m = torch.cat([w * parts[name][1] for name, w in weights.items()], -1) / np.sqrt(sum(w * w for w in weights.values()))
    return z, m


def test_meshes(data: str, count: int, stride: int):
    """(index, Mesh) of test meshes 0, stride, 2 stride, ... (canonical frame, own texture)."""
    dataset = MeshDataset(data, "test")
    for index in range(0, min(count * stride, len(dataset)), stride):
        yield index, item_mesh(dataset[index])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--meshes", type=int, default=12)
    parser.add_argument("--stride", type=int, default=8)
    parser.add_argument("--shares", nargs="+", type=float, default=[0.0, 0.3, 0.5])
    parser.add_argument("--grey-chips", type=int, default=128)
    parser.add_argument("--grey-brightness", action="store_true", help="the brightness fit on the grey layer too")
    parser.add_argument("--engine", default="ours", help="the engine that renders the pictures (ours, gl, cycles, ...)")
    parser.add_argument("--views", type=int, default=1)
    parser.add_argument("--strength", type=float, default=1.0)
    parser.add_argument("--grey-highpass", type=float, default=1.5, help="0: none")
    parser.add_argument("--grey-window", type=float, default=2.0, help="0: none")
    args = parser.parse_args()
    wm = meshseal.load()
    shipped = wm.model
    e = shipped.texture_encoder
    grey = SpreadSpectrumEncoder(e.n_bits, args.grey_chips, "grey", e.texture_psnr, e.window, e.floor, e.seed + 7919)
    grey_reader = copy.deepcopy(shipped)
    grey_reader.texture_encoder = grey
    layer_readers = {"chroma": shipped, "grey": grey_reader}
    renderer = make_renderer(args.engine)
    key = payload.key_seed(None)
    readers = {"chroma": {"chroma": 1.0}, "grey": {"grey": 1.0}, "sum": {"chroma": 1.0, "grey": 1.0}}
    print(f"engine {args.engine}, {args.meshes} test meshes (stride {args.stride}) x {args.views} seed views, 256^2, "
          "camera known")
    print("| grey share | object PSNR | object FLIP | teapot PSNR / FLIP | picture | "
          + " | ".join(f"{r} acc / det" for r in readers) + " | best-of-3 det |")
    print("|---" * (6 + len(readers)) + "|", flush=True)
    for share in args.shares:
        model = TwoLayers(e, grey, share, args.strength)
        with torch.no_grad():
            seen = fixture_visibility(model)
            rows: dict = {}
            for index, mesh in test_meshes(args.data, args.meshes, args.stride):
                generator = torch.Generator().manual_seed(1000 + index)
                message = torch.randint(0, 2, (1, e.n_bits), generator=generator).float()
                texture = mesh.materials[0].texture.permute(2, 0, 1)[None]
                marked = replace(mesh, materials=[meshseal.Material(texture=model(texture, message, None, key)[0]
                                                                    .permute(1, 2, 0).contiguous())])
                cameras, lights = sample_views(args.views, "seed", generator)
                shots = renderer.render(normalize(to_z_up(marked)), cameras, lights, 256, 256, background=(0.5, 0.5, 0.5))
                original = wm.original(mesh)
                for view in range(args.views):
                    png = torch.round(shots[[view], ..., :3].permute(0, 3, 1, 2).clamp(0, 1) * 255) / 255
                    for name, picture in (("PNG", png), ("JPEG 90", jpeg(png, 90)), ("JPEG 75", jpeg(png, 75))):
                        parts = read(layer_readers, original, picture, cameras[[view]], key, args.grey_brightness,
                                     {"highpass": args.grey_highpass or None, "window": args.grey_window or None})
                        ps = []
                        for reader, weights in readers.items():
                            z, m = combine(parts, weights)
                            p = float(payload.detection_pvalue(z, m))
                            ps.append(p)
                            acc = float(((z > 0).double() == message[0]).double().mean())
                            rows.setdefault((name, reader), []).append((acc, payload.detected(p)))
                        rows.setdefault((name, "best"), []).append((0, payload.detected(3 * min(ps))))
        teapot = seen["teapot"]
        for name in ("PNG", "JPEG 90", "JPEG 75"):
            cells = [f"{np.mean([a for a, _ in rows[(name, r)]]):.3f} / {np.mean([d for _, d in rows[(name, r)]]):.2f}"
                     for r in readers]
            best = np.mean([d for _, d in rows[(name, "best")]])
            print(f"| {share} | {seen['psnr_object']:.2f} | {seen['flip_object']:.4f} | {teapot['psnr_object']:.2f} / "
                  f"{teapot['flip_object']:.4f} | {name} | " + " | ".join(cells) + f" | {best:.2f} |", flush=True)


if __name__ == "__main__":
    main()
