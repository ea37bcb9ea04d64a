"""Issue #14: every command on every hostile input of the generated corpus (tests/corpus_gen.py).

Each group of runs goes through one process (tests/corpus_driver.py) that calls the CLI in turn. Every
run must finish within RUN_LIMIT seconds without a traceback and leave its input folder unchanged; a
hostile input gives exit 2 and exactly one `meshseal: error:` line naming a file of the run, with nothing
left in its output folder; a valid control succeeds and writes its outputs completely.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import corpus_driver
import corpus_gen

RUN_LIMIT = 20  # seconds for one run (generous: the machine may be shared); hostile runs take milliseconds
PROCESS_LIMIT = 300  # backstop for a whole group
DRIVER = Path(__file__).with_name("corpus_driver.py")


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    return corpus_gen.build(tmp_path_factory.mktemp("corpus") / "c")


def _problems(run: dict, result: dict | None) -> list[str]:
    if result is None:
        return ["did not finish (the group process was killed or crashed)"]
    problems = []
    if result["crash"]:
        problems.append(f"escaped main(): {result['crash'].strip().splitlines()[-1]}")
    if result["seconds"] > RUN_LIMIT:
        problems.append(f"took {result['seconds']} s")
    if result["changed"]:
        problems.append("an input file changed")
    lines = result["stderr"].strip().splitlines()
    if "Traceback" in result["stderr"] or any(not line.startswith("meshseal: ") for line in lines):
        problems.append(f"stderr is not meshseal's one-line messages: {result['stderr'][-300:]!r}")
    errors = [line for line in lines if line.startswith("meshseal: error: ")]
    if run["expect"] == "error":
        if result["code"] != 2 or len(errors) != 1:
            problems.append(f"expected exit 2 and one error line, got {result['code']} and {errors}")
        elif run["watch"] not in errors[0] and run["out"] not in errors[0] and run["cls"] != "bad argument":
            problems.append(f"the error names no file of the run: {errors[0]}")
        if result["left"]:
            problems.append(f"left output behind: {result['left']}")
    elif run["expect"] == "ok":  # detect's exit 1 is a picture read and found unmarked
        if result["code"] not in ((0, 1) if run["argv"][0] == "detect" else (0,)) or errors:
            problems.append(f"expected success, got {result['code']}: {result['stderr'][-300:]!r}")
        missing = set(run["outputs"]) - set(result["left"])
        if missing or any(name.endswith(".tmp") for name in result["left"]):
            problems.append(f"outputs missing or partial: {sorted(missing)} / {result['left']}")
    elif result["code"] not in (0, 1, 2):
        problems.append(f"exit {result['code']}")
    return problems


@pytest.mark.heavy
@pytest.mark.parametrize("group", corpus_gen.GROUPS)
def test_every_command_on_every_case(corpus, group, tmp_path):
    runs = [run for run in corpus.runs if run["group"] == group]
    assert runs
    runs_file = tmp_path / "runs.json"
    runs_file.write_text(json.dumps(runs))
    shared = corpus.root / group / "_mesh"  # the mesh the picture runs read
    before = corpus_driver.snapshot(shared)
    env = {key: value for key, value in os.environ.items() if key != "MESHSEAL_DEBUG"}
    try:
        process = subprocess.run([sys.executable, str(DRIVER), str(runs_file), str(RUN_LIMIT)], capture_output=True,
                                 text=True, timeout=PROCESS_LIMIT, env=env)
        output, tail = process.stdout, process.stderr[-2000:]
    except subprocess.TimeoutExpired as expired:
        output, tail = (expired.stdout or b"").decode(), "killed after the process limit"
    results = {}
    for line in output.splitlines():
        if line.startswith("{"):
            result = json.loads(line)
            results[result["id"]] = result
    failures = [f"{run['id']} ({' '.join(run['argv'][:1])}): {problem}"
                for run in runs for problem in _problems(run, results.get(run["id"]))]
    assert not failures, f"{len(failures)} of {len(runs)} runs failed:\n" + "\n".join(failures[:40]) + f"\n{tail}"
    assert corpus_driver.snapshot(shared) == before
    if group == "pictures":
        mixed = results["pictures/mixed_call/detect"]
        read = [line.split(":")[0] for line in mixed["stdout"].splitlines()]
        assert all(Path(name).name in ("a.png", "c.png") for name in read)
        assert "b.png" in mixed["stderr"]


def test_corpus_size_and_classes(corpus):
    counts = corpus_gen.counts(corpus)
    hostile = sum(1 for _, is_hostile in corpus.cases.values() if is_hostile)
    assert hostile >= 200
    for cls in ("truncated", "header counts", "bad index", "bad document", "corrupt container", "special file",
                "broken texture", "broken picture", "output path", "control", "documented recovery"):
        assert counts.get(cls, 0) >= 3, cls
    groups = {case.split("/")[0] for case, (_, is_hostile) in corpus.cases.items() if is_hostile}
    assert groups == set(corpus_gen.GROUPS)


def test_every_picture_format_converts_to_the_same_rgb(corpus, tmp_path):
    """Grey, 16-bit, palette, CMYK, progressive, animated, TIFF, WebP, BMP: read once into float RGB in
    [0, 1] that matches the picture (JPEGs within their loss; grey ones against the grey reference)."""
    from meshseal.reading.pictures import load_picture

    reference = np.asarray(Image.open(corpus.reference).convert("RGB"), dtype=np.float32) / 255
    grey = np.asarray(Image.open(corpus.reference).convert("L"), dtype=np.float32) / 255
    tolerance = {"cmyk_jpeg": 0.03, "progressive_jpeg": 0.03, "animated_gif": 0.05, "palette_transparency": 0.05}
    for name, data in corpus.odd_pictures.items():
        path = tmp_path / f"{name}.img"
        path.write_bytes(data)
        pixels, mask, _ = load_picture(path)
        assert pixels.dtype == np.float32 and pixels.shape == reference.shape, name
        assert 0.0 <= pixels.min() and pixels.max() <= 1.0, name
        expected = np.repeat(grey[..., None], 3, axis=-1) if name == "rgb16_tiff" else reference
        error = float(np.abs(pixels - expected).mean())
        assert error <= tolerance.get(name, 0.002), (name, error)
        if name == "palette_transparency":  # palette entry 0 (the black background) is transparent
            assert mask is not None and 0.05 < mask.mean() < 0.95
        else:
            assert mask is None, name
