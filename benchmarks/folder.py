"""`meshseal detect FOLDER --mesh MESH` from the command line (issue #46): the wall time of the whole
command on a folder of pictures without metadata, for this tree and a reference commit in one run, and
whether both print the same lines.

The folder (made once with this tree's code): `--marked` views of the bunny fixture marked with "ab42"
(`meshseal embed`, `meshseal render --views`, 256^2, seeded) and `--others` views of the other textured
fixtures (suzanne, teapot, crate, deck chair, in turn), each saved as an 8-bit PNG without metadata, so
that every picture is registered against the bunny: the marked ones read their mark, the others are what
a scan for one asset mostly meets. Each code runs the command in a fresh process with its own thread
policy (`OMP_NUM_THREADS`, `NUMBA_NUM_THREADS` and `MESHSEAL_THREADS` removed from its environment), the
codes in turn, `--rounds` times (the order swapped each round); `uptime` before each command.

    python benchmarks/folder.py [--ref COMMIT] [--marked 2] [--others 18] [--rounds 1] [--work DIR]
                                [--tree-args "--quick"]

`--tree-args`: more arguments for this tree's command only (`--ref HEAD --tree-args --quick`: the same
code, a quick scan against a full one).

Last line: `seconds=` (this tree, median over rounds), `ref_seconds=`, `xref=` their ratio, `detected=`
(this tree's lines that say detected), `same_lines=` (1 where both codes print the same lines, their
numbers within 2 %; the lines that differ are printed above it).
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "tests" / "fixtures"
OTHERS = ("suzanne.glb", "teapot/teapot.obj", "sh3d_crate/crate.obj", "sh3d_deckChair/deckChair.obj")


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def cli(source: Path) -> tuple[list[str], dict]:
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "MESHSEAL_THREADS")}
    return [sys.executable, "-m", "meshseal.cli"], env | {"PYTHONPATH": str(source)}


def prepare(folder: Path, marked: int, others: int) -> None:
    """The scan's pictures, without metadata."""
    from PIL import Image

    command, env = cli(ROOT / "src")
    views = folder / "views"
    views.mkdir(parents=True)
    run = lambda *argv: subprocess.run(command + list(argv), env=env, check=True, capture_output=True)  # noqa: E731
    run("embed", str(FIXTURES / "bunny.glb"), "-o", str(views / "bunny_marked.glb"), "--message", "ab42", "--views", "0")
    run("render", str(views / "bunny_marked.glb"), "-o", str(views / "bunny.png"), "--views", str(max(marked, 2)),
        "--seed", "5", "--width", "256", "--height", "256")
    for k in range(others):
        name = OTHERS[k % len(OTHERS)]
        run("render", str(FIXTURES / name), "-o", str(views / f"other_{k:02d}.png"), "--views", "2", "--seed", str(k),
            "--width", "256", "--height", "256")
    pictures = folder / "pictures"
    pictures.mkdir()
    for k in range(marked):
        Image.open(views / f"bunny_{k}.png").convert("RGB").save(pictures / f"bunny_{k:02d}.png")
    for k in range(others):
        Image.open(views / f"other_{k:02d}_0.png").convert("RGB").save(pictures / f"other_{k:02d}.png")


def detect(source: Path, pictures: Path, extra: list[str] = ()) -> tuple[float, list[str]]:
    command, env = cli(source)
    start = time.perf_counter()
    out = subprocess.run(command + ["detect", str(pictures), "--mesh", str(FIXTURES / "bunny.glb"), *extra], env=env,
                         capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if out.returncode not in (0, 1):
        raise SystemExit(f"meshseal detect failed under {source}:\n{out.stderr[-2000:]}")
    return seconds, out.stdout.splitlines()


NUMBER = re.compile(r"\d+\.?\d*(?:e[-+]?\d+)?")


def same_line(a: str, b: str) -> bool:
    """The same words, and numbers (p-values, overlaps) within 2 % of each other: a worker's one thread
    moves a sum's last digits, and a rounded figure can fall either side of its last printed digit."""
    if NUMBER.sub("#", a) != NUMBER.sub("#", b):
        return False
    pairs = zip((float(x) for x in NUMBER.findall(a)), (float(x) for x in NUMBER.findall(b)))
    return all(abs(x - y) <= 0.02 * max(abs(x), abs(y)) + 1e-3 for x, y in pairs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--ref", default="HEAD~1")
    parser.add_argument("--marked", type=int, default=2)
    parser.add_argument("--others", type=int, default=18)
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--work", type=Path, default=None, help="folder for the pictures (kept, reused)")
    parser.add_argument("--tree-args", default="", help="more arguments for this tree's `meshseal detect` only")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="folderbench_"))
    if not (work / "pictures").is_dir():
        prepare(work, args.marked, args.others)
    pictures = work / "pictures"
    with tempfile.TemporaryDirectory() as temporary:
        ref_root = Path(temporary)
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", args.ref, "src"], check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(ref_root)], input=archive, check=True)
        label = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", args.ref], capture_output=True,
                               text=True).stdout.strip()
        codes = {f"ref {label}": ref_root / "src", "tree": ROOT / "src"}
        print(f"{len(list(pictures.glob('*.png')))} pictures in {pictures} ({args.marked} of the marked bunny); "
              f"ref {label} against this tree{' with ' + args.tree_args if args.tree_args else ''}", flush=True)
        seconds = {code: [] for code in codes}
        lines = {}
        for round_ in range(args.rounds):
            for code in (list(codes) if round_ % 2 == 0 else list(codes)[::-1]):
                print(f"  {uptime()}", flush=True)
                value, lines[code] = detect(codes[code], pictures, args.tree_args.split() if code == "tree" else [])
                seconds[code].append(value)
                detected = sum(": detected" in line for line in lines[code])
                print(f"  {code}: {value:.1f} s, {detected} of {len(lines[code])} detected", flush=True)
    print(f"  {uptime()}")
    tree, ref = (statistics.median(seconds[code]) for code in ("tree", f"ref {label}"))
    pairs = list(zip(lines["tree"], lines[f"ref {label}"]))
    same = len(lines["tree"]) == len(lines[f"ref {label}"]) and all(same_line(a, b) for a, b in pairs)
    for mine, theirs in pairs:
        if not same_line(mine, theirs):
            print(f"  differs:\n    tree: {mine}\n    ref:  {theirs}")
    detected = sum(": detected" in line for line in lines["tree"])
    print(f"seconds={tree:.1f} ref_seconds={ref:.1f} xref={tree / ref:.3f} detected={detected} same_lines={int(same)}")


if __name__ == "__main__":
    main()
