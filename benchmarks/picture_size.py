"""`meshseal detect` on pictures of the sizes the web has (issue #46): the bunny fixture marked ("ab42",
`meshseal embed --views 0`), rendered by `meshseal render` from its default camera at each size, read
from the command line with its camera in the PNG and again from a copy without metadata (registered).
Each figure is one fresh process: wall seconds (start-up included), peak memory (the child's maximum
resident set) and what it printed. The load average is printed at the start and the end.

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python benchmarks/picture_size.py [--sizes 256 512 1024 2048]

Last line: `camera_known_s_<S>= registered_s_<S>= camera_known_mb_<S>= registered_mb_<S>=` per size.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BUNNY = ROOT / "tests" / "fixtures" / "bunny.glb"


def meshseal() -> list[str]:
    found = shutil.which("meshseal", path=str(Path(sys.executable).parent)) or shutil.which("meshseal")
    return [found] if found else [sys.executable, "-c", "import sys; from meshseal.cli import main; sys.exit(main())"]


# A fresh wrapper per command, so that the peak it reports (its children's, KB on Linux) is that command's alone.
WRAPPER = ("import resource, subprocess, sys; done = subprocess.run(sys.argv[1:], capture_output=True, text=True); "
           "sys.stdout.write((done.stdout + done.stderr).strip().splitlines()[-1:][0] if (done.stdout + done.stderr).strip() "
           "else f'exit {done.returncode}'); print(); print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")


def timed(command: list[str]) -> tuple[float, float, str]:
    """Wall seconds, the command's peak resident memory in MB, and its last output line."""
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", WRAPPER, *command], capture_output=True, text=True, check=True)
    seconds = time.perf_counter() - started
    line, peak = done.stdout.strip().splitlines()[-2:]
    return seconds, int(peak) / 1024, line


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024, 2048])
    args = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")
    from PIL import Image

    print(f"load average at start: {os.getloadavg()}")
    command, figures = meshseal(), {}
    with tempfile.TemporaryDirectory() as folder:
        work = Path(folder)
        marked = work / "bunny_marked.glb"
        subprocess.run(command + ["embed", str(BUNNY), "-o", str(marked), "--message", "ab42", "--views", "0"],
                       check=True, capture_output=True)
        print("| size | camera known: s / peak MB | registered: s / peak MB | camera known reads | registered reads |")
        print("|---|---|---|---|---|")
        for size in sorted(args.sizes):
            picture = work / f"bunny_{size}.png"
            subprocess.run(command + ["render", str(marked), "-o", str(picture), "--width", str(size), "--height",
                                      str(size)], check=True, capture_output=True)
            bare = work / f"bunny_{size}_bare.png"
            with Image.open(picture) as image:
                image.convert("RGB").save(bare)  # the pixels alone, no camera chunk
            known = timed(command + ["detect", str(picture), "--mesh", str(BUNNY)])
            registered = timed(command + ["detect", str(bare), "--mesh", str(BUNNY)])
            figures[size] = (known, registered)
            print(f"| {size}^2 | {known[0]:.2f} / {known[1]:.0f} | {registered[0]:.2f} / {registered[1]:.0f} | "
                  f"{known[2].split(': ', 1)[-1]} | {registered[2].split(': ', 1)[-1]} |", flush=True)
    print(f"load average at end: {os.getloadavg()}")
    print(" ".join(f"camera_known_s_{s}={k[0]:.2f} registered_s_{s}={r[0]:.2f} camera_known_mb_{s}={k[1]:.0f} "
                   f"registered_mb_{s}={r[1]:.0f}" for s, (k, r) in figures.items()))


if __name__ == "__main__":
    main()
