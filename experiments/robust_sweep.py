"""Which spread-spectrum mark survives the road to the web (issue 45): JPEG 90 / 75 / 50 and WebP 80.

Everything goes through the CLI (no import of meshseal): each configuration is configs/default.yaml
with some `model:` knobs changed, built by `meshseal train` (steps 0: the spread mark is built, not
learned) and read by `meshseal eval --attacks ... --json` with the camera known, strength 1 throughout
(`--max-flip 0`: no per-mesh FLIP budget, so that a configuration's strength is its texture PSNR and
the curve is detection against the FLIP it costs). Results are cached per (configuration, meshes) in
the run folder; the script ends with one Markdown table.

Object FLIP p95 (`--p95`): `meshseal eval` prints the mean object FLIP only, so the per-mesh FLIP is
recovered from the means over the first k meshes, k = 1..N (mesh k's FLIP = k m_k - (k - 1) m_(k-1);
with `--attacks` eval reads mesh by mesh, and each mesh's view and mark do not depend on N; the last
running mean is checked against the attacks eval's). That costs N evals: use it on 30 meshes.

The tables of issue 45's sweep (the CLI of commit 5791fc4, as the package was being moved):

    python experiments/robust_sweep.py --data data --meshes 30 --set first --commit 5791fc4
    python experiments/robust_sweep.py --data data --meshes 30 --set loud --psnr 34 28 --commit 5791fc4
    python experiments/robust_sweep.py --data data --meshes 100 --set final --commit 5791fc4
    python experiments/robust_sweep.py --data data --meshes 100 --set curve --psnr 37 34 31 28 --commit 5791fc4
    python experiments/robust_sweep.py --data data --meshes 30 --set mask --commit 5791fc4
    python experiments/robust_sweep.py --data data --meshes 30 --config default: \
        --config grey128@34:mark_colour=grey,texture_psnr=34 --p95 --commit 5791fc4

Run one at a time (OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 are set for the children).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

ATTACKS = ("none", "jpeg90", "jpeg75", "jpeg50", "webp80")
ROOT = Path(__file__).resolve().parents[1]

# Cell grids that adapt to the texture's magnification so that a cell is a few picture pixels wide
# in a standard 256^2 view (`models.spread.cell_pixels` measures a `chips` cell there).
GRID64 = {"chips": 64, "coarse_chips": 32, "coarse_below": 2.0, "fine_chips": 128, "fine_above": 6.0}
GRID32 = {"chips": 32, "coarse_chips": 16, "coarse_below": 3.0, "fine_chips": 64, "fine_above": 8.0}
GREY = {"mark_colour": "grey"}

SETS = {
    "first": {
        "default": {},
        "grey128": GREY,
        "grey64": GREY | GRID64,
        "grey32": GREY | GRID32,
        "by64": GRID64,
        "by32": GRID32,
        "rg32": {"mark_colour": "red-green"} | GRID32,
        "grey64_floor0.1": GREY | {"activity_floor": 0.1} | GRID64,
    },
    # the most promising of the first set, louder (`--psnr 34 28`): where does JPEG start to read?
    "loud": {
        "default": {},
        "grey128": GREY,
        "by64": GRID64,
        "by32": GRID32,
        "rg32": {"mark_colour": "red-green"} | GRID32,
    },
    # refined on 100 meshes: the shipped mark, the best at the invisibility budget, the coarse chroma
    "final": {
        "default": {},
        "grey128": GREY,
        "by64": GRID64,
    },
    # the curve of the best (`--psnr 37 34 31 28`)
    "curve": {"grey128": GREY},
    # more activity masking at the curve's FLIP 0.03 point, and the coarse chroma at that FLIP
    "mask": {
        "grey128_floor0.1@31": GREY | {"activity_floor": 0.1, "texture_psnr": 31.0},
        "grey128_w9f0.1@31": GREY | {"activity_window": 9, "activity_floor": 0.1, "texture_psnr": 31.0},
        "grey128@31": GREY | {"texture_psnr": 31.0},
        "by64@37": GRID64 | {"texture_psnr": 37.0},
    },
}


def parse_config(text: str) -> tuple[str, dict]:
    """'name:key=value,key=value' -> (name, knobs), values parsed as YAML scalars."""
    name, _, rest = text.partition(":")
    knobs = {}
    for pair in filter(None, rest.split(",")):
        key, _, value = pair.partition("=")
        knobs[key.strip()] = yaml.safe_load(value)
    return name, knobs


PACKAGE: Path | None = None  # --commit: the CLI of the package as committed there, not the working tree's


def snapshot(commit: str, out: Path) -> Path:
    """src/ as committed at `commit`, extracted (once) under out/package_<sha>: its CLI is what runs."""
    sha = subprocess.run(["git", "rev-parse", commit], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()
    folder = out / f"package_{sha[:12]}"
    if not (folder / "src" / "meshseal" / "cli.py").exists():
        folder.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "archive", sha, "src"], cwd=ROOT, capture_output=True, check=True).stdout
        subprocess.run(["tar", "-x", "-C", str(folder)], input=archive, check=True)
    return folder / "src"


def run(command: list[str], log: Path, tries: int = 6) -> str:
    """Runs a CLI command (one thread); a failure (e.g. the package mid-edit) is retried a minute later."""
    env = os.environ | {"OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
    if PACKAGE is not None and command[0] == "meshseal":
        command = [sys.executable, "-m", "meshseal.cli", *command[1:]]
        env["PYTHONPATH"] = str(PACKAGE)
    for attempt in range(tries):
        with open(log, "a") as handle:
            handle.write("$ " + " ".join(command) + "\n")
            done = subprocess.run(command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=handle, text=True,
                                  check=False)
            handle.write(done.stdout[-2000:] + "\n")
        if not done.returncode:
            return done.stdout
        if attempt + 1 < tries:
            time.sleep(60)
    raise RuntimeError(f"{' '.join(command)} failed ({done.returncode}); see {log}")


def build(name: str, knobs: dict, out: Path) -> Path:
    """configs/default.yaml with `knobs` in its model section -> out/name/model.safetensors."""
    folder = out / name
    folder.mkdir(parents=True, exist_ok=True)
    config = yaml.safe_load((ROOT / "configs" / "default.yaml").read_text())
    config["name"] = name
    config["model"].update(knobs)
    path = folder / "config.yaml"
    text = yaml.safe_dump(config, sort_keys=False)
    model = folder / "model.safetensors"
    if not model.exists() or not path.exists() or path.read_text() != text:
        for stale in folder.glob("eval_*.json"):  # read from another model
            stale.unlink()
        path.write_text(text)
        run(["meshseal", "train", "--config", str(path), "--out", str(folder)], folder / "log.txt")
    return model


def evaluate(model: Path, args, meshes: int, attacks: tuple[str, ...], tag: str) -> dict:
    """`meshseal eval` of `model` on the first `meshes` test meshes, cached in the model's folder."""
    cache = model.parent / f"eval_{tag}_{meshes}_{args.size}_{args.views}.json"
    if cache.exists():
        return json.loads(cache.read_text())
    command = ["meshseal", "eval", "--model", str(model), "--data", args.data, "--meshes", str(meshes),
               "--size", str(args.size), "--views", str(args.views), "--max-flip", "0", "--json"]
    if attacks:
        command += ["--attacks", ",".join(attacks)]
    started = time.time()
    result = json.loads(run(command, model.parent / "log.txt"))
    result["wall_seconds"] = time.time() - started
    cache.write_text(json.dumps(result))
    return result


def flip_per_mesh(model: Path, args) -> np.ndarray:
    """Each of the first N meshes' object FLIP, from the running means of `meshseal eval`."""
    # `--attacks none`: the per-mesh path of the attacks eval (without attacks eval batches meshes
    # and draws other views, so that its running means are not per-mesh sums)
    means = [evaluate(model, args, k, ("none",), "flip")["flip_object"] for k in range(1, args.meshes + 1)]
    totals = np.array(means) * np.arange(1, args.meshes + 1)
    return np.diff(np.concatenate([[0.0], totals]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default="data")
    parser.add_argument("--meshes", type=int, default=30)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--views", type=int, default=1)
    parser.add_argument("--set", choices=sorted(SETS), action="append", default=[])
    parser.add_argument("--config", action="append", default=[], help="name:key=value,... (model knobs)")
    parser.add_argument("--psnr", type=float, nargs="*", default=[],
                        help="also each configuration at these texture PSNRs (name@PSNR)")
    parser.add_argument("--p95", action="store_true", help="object FLIP p95 from per-mesh FLIP (N evals)")
    parser.add_argument("--out", default="runs/robust")
    parser.add_argument("--table", default=None, help="also write the table here")
    parser.add_argument("--commit", default=None,
                        help="run the CLI of src/ as committed at this revision (e.g. HEAD), not the working tree's")
    args = parser.parse_args()
    global PACKAGE
    if args.commit:
        PACKAGE = snapshot(args.commit, ROOT / args.out)

    configs: dict[str, dict] = {}
    for name in args.set:
        configs |= SETS[name]
    configs |= dict(parse_config(text) for text in args.config)
    for name, knobs in list(configs.items()):
        for psnr in args.psnr:
            configs[f"{name}@{psnr:g}"] = knobs | {"texture_psnr": psnr}

    out = ROOT / args.out
    header = ("| config | knobs | texture PSNR | object FLIP mean | FLIP p95 | object PSNR | "
              + " | ".join(f"{a} det / exact" for a in ATTACKS) + " | meshes |")
    lines = [header, "|" + "---|" * (header.count("|") - 1)]
    for name, knobs in configs.items():
        model = build(name, knobs, out)
        result = evaluate(model, args, args.meshes, ATTACKS, "attacks")
        p95 = None
        if args.p95:
            flips = flip_per_mesh(model, args)
            if abs(flips.mean() - result["flip_object"]) > 1e-6 or flips.min() < 0:
                raise RuntimeError(f"{name}: per-mesh FLIP does not add up ({flips.mean()} vs {result['flip_object']})")
            p95 = float(np.percentile(flips, 95))
        cells = [f"{result['attacks'][a]['detected']:.2f} / {result['attacks'][a]['exact']:.2f}" for a in ATTACKS]
        shown = ", ".join(f"{k}={v}" for k, v in knobs.items()) or "(default)"
        lines.append(f"| {name} | {shown} | {result['psnr_texture_shown']:.1f} | {result['flip_object']:.4f} | "
                     + ("-" if p95 is None else f"{p95:.4f}") + f" | {result['psnr_object']:.2f} | "
                     + " | ".join(cells) + f" | {result['n_meshes']} |")
        print(lines[-1], file=sys.stderr, flush=True)
    table = "\n".join(lines)
    print(table)
    if args.table:
        Path(args.table).write_text(table + "\n")


if __name__ == "__main__":
    main()
