"""The fine grid's cell sums also read blurred (a matched template for a texture marked on 512^2 cells
and halved after: the halving spreads each cell over its neighbours), as a third grid under Bonferroni:
`robust_curve.py` run with `models.spread.SMOOTHED_FINE_SIGMA` set. Needs commit 2849a43's
`models/spread.py` (the experiment was not taken: docs/mark.md, Alternatives measured).

    python experiments/smoothed_fine.py SIGMA --config configs/default.yaml --data data --kind magnified
        --meshes 60 --psnr 40 --colours grey --attacks none,texture_half
"""

import runpy
import sys
from pathlib import Path

import meshseal.models.spread as spread

if not hasattr(spread, "SMOOTHED_FINE_SIGMA"):
    sys.exit("this experiment needs commit 2849a43's src/meshseal/models/spread.py (git checkout 2849a43 -- src/meshseal/models/spread.py)")
spread.SMOOTHED_FINE_SIGMA = float(sys.argv[1])
sys.argv = ["robust_curve.py"] + sys.argv[2:]
runpy.run_path(str(Path(__file__).with_name("robust_curve.py")), run_name="__main__")
