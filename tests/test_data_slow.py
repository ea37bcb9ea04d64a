"""The real thing: `meshseal data build` from Debian packages (network, ~2 GB download, minutes).

Excluded from the default run (pytest.ini: -m 'not slow'); run with `pytest -m slow tests/test_data_slow.py`.
It uses the normal download cache (~/.cache/meshseal/debs, or $MESHSEAL_DATA_CACHE) and builds a small
subset of every source into a temporary folder.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow


@pytest.mark.skipif(shutil.which("apt-get") is None, reason="needs apt-get (Debian's package archive)")
def test_real_build_from_debian_packages(tmp_path):
    cache = os.environ.get("MESHSEAL_DATA_CACHE", str(Path.home() / ".cache" / "meshseal" / "debs"))
    out = tmp_path / "data"
    run = subprocess.run([sys.executable, "-m", "meshseal.data.cli", "data", "build", "--out", str(out),
                          "--cache", cache, "--max-per-source", "20", "--pool-size", "60"],
                         capture_output=True, text=True, timeout=3600)
    assert run.returncode == 0, run.stderr[-2000:]
    stats = subprocess.run([sys.executable, "-m", "meshseal.data.cli", "data", "stats", str(out), "--json"],
                           capture_output=True, text=True, timeout=600)
    assert stats.returncode == 0, stats.stderr
    result = json.loads(stats.stdout)
    assert result["n_train"] + result["n_test"] >= 50
    assert result["n_textures"] == 60
    assert set(result["source"]) == {"sweethome3d-furniture", "flightgear-data-models", "0ad-data"}
    assert {"CC0-1.0", "CC-BY-3.0", "GPL-2+", "CC-BY-SA-3.0"} <= set(result["license"])
    assert result["texture_kind"].get("own", 0) > 0
