"""How much of a mark of square cells each codec keeps, by the cells' size in the picture.

Each of the first N texture images of --data (resized to 256^2) is the host; a random +-1 pattern of
cells `c` pixels wide, 2 levels in every channel (a grey mark, about a luminance mark's size in a
picture), is added and the picture saved 8-bit; both the marked and the plain host go through each
codec (Pillow's defaults: JPEG 4:2:0) and the difference of the two decoded pictures, in luminance, is
projected on the pattern: the share of the mark's amplitude the codec kept where the host is known
exactly (what an informed reading can hope for; 1 = all of it). Seeded.

    python experiments/codec_survival.py --data data [--images 12] [--cells 1 2 3 4 6 8 12]
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import numpy as np
from PIL import Image

CODECS = {"JPEG 90": ("JPEG", 90), "JPEG 75": ("JPEG", 75), "JPEG 50": ("JPEG", 50), "WebP 80": ("WEBP", 80)}
LUMA = np.array([0.299, 0.587, 0.114])


def round_trip(picture: np.ndarray, fmt: str, quality: int) -> np.ndarray:
    buffer = io.BytesIO()
    Image.fromarray(picture).save(buffer, format=fmt, quality=quality)
    buffer.seek(0)
    with Image.open(buffer) as decoded:
        return np.asarray(decoded.convert("RGB"), dtype=np.float64)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--images", type=int, default=12)
    parser.add_argument("--cells", type=int, nargs="+", default=[1, 2, 3, 4, 6, 8, 12])
    parser.add_argument("--amplitude", type=float, default=2.0, help="the mark's amplitude, 8-bit levels")
    args = parser.parse_args()
    files = sorted((args.data / "textures").iterdir())[:args.images]
    rng = np.random.default_rng(0)
    print("| cell width (px) | " + " | ".join(CODECS) + " |")
    print("|---|" + "---|" * len(CODECS))
    for cell in args.cells:
        kept = {name: [] for name in CODECS}
        for path in files:
            with Image.open(path) as image:
                host = np.asarray(image.convert("RGB").resize((256, 256)), dtype=np.float64)
            side = -(-256 // cell)
            mark = rng.choice([-1.0, 1.0], size=(side, side)).repeat(cell, 0).repeat(cell, 1)[:256, :256] * args.amplitude
            marked = np.clip(np.round(host + mark[..., None]), 0, 255).astype(np.uint8)
            plain = np.clip(np.round(host), 0, 255).astype(np.uint8)
            for name, (fmt, quality) in CODECS.items():
                left = (round_trip(marked, fmt, quality) - round_trip(plain, fmt, quality)) @ LUMA
                kept[name].append(float((left * mark).sum() / (mark * mark).sum()))
        print(f"| {cell} | " + " | ".join(f"{np.mean(v):.2f}" for v in kept.values()) + " |", flush=True)
    print(f"\n({len(files)} texture images of {args.data} at 256^2, amplitude {args.amplitude:g} levels)")


if __name__ == "__main__":
    main()
