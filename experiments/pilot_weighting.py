"""`robust_curve.py` with the message's cells weighted by the mark's local strength as the pilot shows it
(maximal-ratio combining): on each grid, the pilot's cells correlated with the key's signs, averaged over
a Gaussian window of PW_SIGMA cells, floored at 0, divided by the local mean of every visible cell's
square (the cells' noise), scales each message cell's sum before the bits' tests. The weights depend on
the picture and the pilot's signs alone, never on the message cells' signs, so the bits' exact null
holds; the pilot's own test is unchanged. PW_FLOOR keeps that share of the mean weight everywhere.

    PW_SIGMA=3 PW_FLOOR=0.1 python experiments/pilot_weighting.py --config configs/default.yaml --data data --meshes 100 --psnr 40 --colours grey
"""
import os
import runpy
import sys
from pathlib import Path

import torch

import meshseal.methods.spread as S
from meshseal.imaging import gaussian_blur
from meshseal.models.spread import split_grids

SIGMA = float(os.environ.get("PW_SIGMA", "3"))
FLOOR = float(os.environ.get("PW_FLOOR", "0.1"))
_soft_bits = S.SpreadMethod.soft_bits


def weighted(encoder, sums: torch.Tensor, key_seed) -> torch.Tensor:
    """One grid's cell sums (1, C*C) with the message's cells scaled by the pilot's local strength."""
    chips = int(round(sums.shape[1] ** 0.5))
    assign, sign = encoder.pattern(key_seed, chips)
    x = sums[0].double()
    pilot = (assign == encoder.n_bits).double()
    seen = (x != 0).double()
    plane = lambda v: v.reshape(1, 1, chips, chips).float()  # noqa: E731
    blur = lambda v: gaussian_blur(plane(v), SIGMA).reshape(-1).double()  # noqa: E731
    strength = blur(x * sign.double() * pilot) / blur(pilot * seen).clamp_min(1e-9)
    noise = blur(x * x) / blur(seen).clamp_min(1e-9)
    weight = strength.clamp_min(0.0) / noise.clamp_min(1e-12)
    mean = weight[seen.bool()].mean() if bool(seen.any()) else weight.new_tensor(1.0)
    weight = weight + FLOOR * mean
    return torch.where(pilot.bool(), x, x * weight)[None].to(sums.dtype)


def soft_bits(self, evidence, key, expected):
    key_seed = self.key_seed(key)
    if not self.encoder.pilot_slots:
        return _soft_bits(self, evidence, key, expected)
    parts = [weighted(self.encoder, part, key_seed) for part in split_grids(self.encoder, evidence)]
    return _soft_bits(self, torch.cat(parts, 1), key, expected)


S.SpreadMethod.soft_bits = soft_bits
sys.argv = ["robust_curve.py"] + sys.argv[1:]
runpy.run_path(str(Path(__file__).with_name("robust_curve.py")), run_name="__main__")
