"""`robust_curve.py` with each picture's cell sums high-passed in the cell domain before every test: each
visible cell minus K times the mean of its visible neighbours within R cells (a transform of the picture
alone, so the exact null holds). Measured, not taken (docs/mark.md, "Alternatives measured").

    CELLHP_K=1 CELLHP_R=1 python experiments/cell_highpass.py --config configs/default.yaml --data data --meshes 100 --psnr 40 --colours grey
"""
import os
import runpy
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

import meshseal.methods.spread as S
from meshseal.models.spread import split_grids

K = float(os.environ.get("CELLHP_K", "1"))
R = int(os.environ.get("CELLHP_R", "1"))
_orig = S.SpreadMethod.evidence

def _hp(sums):
    c = int(round(sums.numel() ** 0.5))
    x = sums.reshape(1, 1, c, c).double()
    seen = (x != 0).double()
    k = 2 * R + 1
    kernel = torch.ones(1, 1, k, k, dtype=x.dtype); kernel[0, 0, R, R] = 0
    total = F.conv2d(x, kernel, padding=R); count = F.conv2d(seen, kernel, padding=R)
    mean = total / count.clamp_min(1)
    y = (x - K * mean) * seen
    return y.reshape(-1).to(sums.dtype)

def evidence(self, original, picture, camera):
    ev = _orig(self, original, picture, camera)
    parts = split_grids(self.encoder, ev[None])
    return torch.cat([_hp(p[0]) for p in parts])

S.SpreadMethod.evidence = evidence
sys.argv = ["robust_curve.py"] + sys.argv[1:]
runpy.run_path(str(Path(__file__).with_name("robust_curve.py")), run_name="__main__")
