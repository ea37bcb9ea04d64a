"""How much of another engine's fine detail our own render explains: for each mesh of an engine cache
(`experiments/engine_reading.py --cache C`, the unmarked pictures `ENGINE_o`), the picture's luminance
in linear light high-passed (less its Gaussian mean, sigma 1.5 px) over the object's interior (3 px in
from its edge), its RMS, the RMS of its difference to our renderer's picture high-passed alike, and the
RMS left after the best linear filter of ours (least squares over K x K neighbours, `--kernel`): a
share near 1 means no blur, sharpening or shift of our render explains the engine's detail.

    python experiments/engine_detail.py --cache C --meshes 0 1 2 3 4 5 6 7 [--engines workbench eevee cycles] [--kernel 5]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_erosion, gaussian_filter


def linear(values: np.ndarray) -> np.ndarray:
    """8-bit sRGB -> linear light."""
    values = values / 255.0
    return np.where(values <= 0.04045, values / 12.92, ((values + 0.055) / 1.055) ** 2.4)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", type=Path, required=True)
    parser.add_argument("--meshes", type=int, nargs="+", default=list(range(8)))
    parser.add_argument("--engines", nargs="+", default=["workbench", "eevee", "cycles"])
    parser.add_argument("--kernel", type=int, default=5)
    args = parser.parse_args()
    reach = args.kernel // 2
    shares = {engine: [] for engine in args.engines}
    print("| mesh | engine | high-passed RMS (levels) | its difference to ours | left after a "
          f"{args.kernel} x {args.kernel} filter of ours | share left |\n|---|---|---|---|---|---|")
    for mesh in args.meshes:
        cached = np.load(args.cache / f"{mesh}.npz")
        ours = cached["ours_o"].astype(float)
        inside = binary_erosion(np.abs(ours - 127.5).sum(-1) > 3, iterations=3)  # the grey background left out
        inside[:reach + 1], inside[-reach - 1:], inside[:, :reach + 1], inside[:, -reach - 1:] = False, False, False, False
        high = lambda image: image - gaussian_filter(image, 1.5)  # noqa: E731
        ours_high = high(linear(ours).mean(-1))
        rows, columns = np.nonzero(inside)
        design = np.stack([ours_high[rows + dy, columns + dx] for dy in range(-reach, reach + 1)
                           for dx in range(-reach, reach + 1)], 1)
        for engine in args.engines:
            target = high(linear(cached[f"{engine}_o"].astype(float)).mean(-1))[rows, columns]
            coefficients, *_ = np.linalg.lstsq(design, target, rcond=None)
            left = target - design @ coefficients
            rms = lambda x: float(np.sqrt((x ** 2).mean()) * 255)  # noqa: E731
            share = rms(left) / max(rms(target), 1e-9)
            shares[engine].append(share)
            print(f"| {mesh} | {engine} | {rms(target):.2f} | {rms(target - ours_high[rows, columns]):.2f} | "
                  f"{rms(left):.2f} | {share:.2f} |")
    for engine, values in shares.items():
        print(f"{engine}: median share left {np.median(values):.2f} (min {min(values):.2f}, max {max(values):.2f})")


if __name__ == "__main__":
    main()
