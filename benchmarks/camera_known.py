"""Camera-known reading (issue #46), a reference commit and this tree in one run.

Figures, each timed for both codes, alternating code by code and round by round, each in a fresh
child process whose code comes first on PYTHONPATH (the reference exported with `git archive`):

- `picture_ms`: `Watermarker.detect(PATH, original)` of one 256^2 PNG with its camera in the metadata
  (`meshseal render`'s), the original prepared once: the median over the pictures of the folder below,
  after two warm-ups (the renderer's compiled kernels loaded first: the steady state); the child also returns every picture's bits and p-value, compared between codes;
- `folder_per_s`: `meshseal detect FOLDER --mesh MESH --jsonl` on a folder of those pictures, each there
  `--folder-copies` times (default 8: hard links), default workers (this process until one per core
  would read the rest sooner): lines per second over the last half of the lines (a pool, where one
  starts, is running by then); the round's line also gives the seconds from the start to the last line;
- `first_line_s`: from starting `meshseal detect PICTURE --mesh MESH` to its first result line, the
  mesh met before (the load cache, `meshseal.mesh.cache`, holds it: `meshseal embed` put it there);
- `first_line_cold_s`: the same with an empty load cache (a mesh this machine never loaded: trimesh).

Every child runs with bytecode caching on (`child_env`: PYTHONDONTWRITEBYTECODE dropped), as an
installed package runs; the warm-up before the rounds writes each code's caches.

The pictures: the bunny fixture marked (`meshseal embed --message ab42 --views 0`) and rendered from
`--pictures` seeded views (default 64) at 256^2, each with its camera in the PNG. The load average is
printed before each round; other jobs on the machine slow both codes alike only if they run the whole
time, so compare the ratios of a round, not figures across runs.

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python benchmarks/camera_known.py [--ref COMMIT] [--rounds 2]
        [--pictures 64] [--folder-copies 8] [--figures picture,folder,first,cold]

Last line: `picture_ms=... folder_per_s=... first_line_s=...` for this tree and `..._xref=` its ratio
to the reference (medians over rounds), `..._best=` and `..._best_xref=` the same for each code's best
round (on a machine where a process runs fast or slow as a whole, the best rounds compare the code),
and `load=` the one-minute load averages seen.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BUNNY = ROOT / "tests" / "fixtures" / "bunny.glb"


def child_picture(folder: Path) -> dict:
    """Median ms of one camera-known detect over the folder's pictures, and what each read."""
    import meshseal.threads

    meshseal.threads.configure()
    import meshseal

    watermarker = meshseal.load()
    original = watermarker.original(BUNNY)
    try:  # the steady state: the renderer's kernels loaded first where the code loads them when they pay
        from meshseal.render import compiled

        compiled.load()
    except ImportError:
        pass
    pictures = sorted(folder.glob("*.png"))
    for path in pictures[:2]:
        watermarker.detect(path, original)
    times, results = [], {}
    for path in pictures:
        start = time.perf_counter()
        found = watermarker.detect(path, original)
        times.append(1000.0 * (time.perf_counter() - start))
        results[path.name] = (found.bits, found.p_value, found.message)
    return {"value": statistics.median(times), "results": results}


def child_env(source: Path) -> dict:
    """This environment with `source` first on PYTHONPATH and bytecode caching on, as a user's install
    runs: where PYTHONDONTWRITEBYTECODE is set (some sandboxes and CI images set it) every start would
    compile meshseal's own sources again, about a tenth of a second that no installed package pays
    (pip compiles them, or the first import writes them); the warm-up runs below write each code's."""
    env = {name: value for name, value in os.environ.items() if name != "PYTHONDONTWRITEBYTECODE"}
    return dict(env, PYTHONPATH=str(source))


def cli(source: Path) -> tuple[list[str], dict]:
    return [sys.executable, "-m", "meshseal.cli"], child_env(source)


def folder_rate(source: Path, folder: Path) -> tuple[float, float]:
    """Lines per second over the last half of the lines, and the seconds to the last line."""
    command, env = cli(source)
    start = time.perf_counter()
    run = subprocess.Popen(command + ["detect", str(folder), "--mesh", str(BUNNY), "--jsonl"], env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    arrivals, right = [], 0
    for line in run.stdout:
        arrivals.append(time.perf_counter() - start)
        right += json.loads(line).get("message") == "ab42"
    if run.wait() not in (0, 1) or len(arrivals) < 2:
        raise SystemExit(f"meshseal detect FOLDER failed under {source}")
    middle = len(arrivals) // 2
    return (len(arrivals) - 1 - middle) / (arrivals[-1] - arrivals[middle]), arrivals[-1]


def first_line(source: Path, picture: Path, cache: Path) -> float:
    """Seconds from the start to the first line, with the load cache (`mesh.cache`) in `cache`."""
    command, env = cli(source)
    env["MESHSEAL_CACHE"] = str(cache)
    start = time.perf_counter()
    run = subprocess.Popen(command + ["detect", str(picture), "--mesh", str(BUNNY)], env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    run.stdout.readline()
    seconds = time.perf_counter() - start
    run.wait()
    return seconds


def run_child_picture(source: Path, folder: Path) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", str(folder)], env=child_env(source), check=True,
                         capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def load_average() -> float:
    return os.getloadavg()[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ref", default="HEAD~1")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--pictures", type=int, default=64)
    parser.add_argument("--figures", default="picture,folder,first,cold")
    parser.add_argument("--folder-copies", type=int, default=8)
    parser.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        print(json.dumps(child_picture(args.child)))
        return
    figures = args.figures.split(",")
    with tempfile.TemporaryDirectory() as temporary:
        work = Path(temporary)
        ref_root = work / "ref"
        ref_root.mkdir()
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", args.ref, "src"], check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(ref_root)], input=archive, check=True)
        codes = {"ref": ref_root / "src", "tree": ROOT / "src"}
        command, env = cli(codes["tree"])
        cache = work / "cache"  # the load cache: `embed` below fills it with the bunny, as it does for a user
        os.environ["MESHSEAL_CACHE"] = str(cache)
        env["MESHSEAL_CACHE"] = str(cache)
        marked, folder = work / "marked.glb", work / "pictures"
        subprocess.run(command + ["embed", str(BUNNY), "-o", str(marked), "--message", "ab42", "--views", "0"],
                       env=env, check=True, capture_output=True)
        subprocess.run(command + ["render", str(marked), "-o", str(folder / "v.png"), "--views", str(args.pictures),
                                  "--seed", "0", "--width", "256", "--height", "256"], env=env, check=True,
                       capture_output=True)
        picture = sorted(folder.glob("*.png"))[0]
        many = work / "many"
        many.mkdir()
        for copy in range(args.folder_copies):
            for path in sorted(folder.glob("*.png")):
                os.link(path, many / f"c{copy}_{path.name}")
        print(f"ref {args.ref} ({subprocess.run(['git', '-C', str(ROOT), 'rev-parse', '--short', args.ref], capture_output=True, text=True).stdout.strip()}) "
              f"against this tree; {args.pictures} pictures of the marked bunny at 256^2; "
              f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')} NUMBA_NUM_THREADS={os.environ.get('NUMBA_NUM_THREADS')}")
        for code, source in codes.items():  # warm: numba compiles each code's kernels into its cache once
            first_line(source, picture, cache)
        values = {(name, code): [] for name in figures for code in codes}
        loads, results = [], {}
        for round_ in range(args.rounds):
            loads.append(load_average())
            print(f"round {round_ + 1}: uptime: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}")
            for name in figures:
                for code in (codes if round_ % 2 == 0 else list(codes)[::-1]):
                    source = codes[code]
                    total = ""
                    if name == "picture":
                        out = run_child_picture(source, folder)
                        value, results[code] = out["value"], out["results"]
                    elif name == "folder":
                        value, seconds = folder_rate(source, many)
                        total = f"  ({args.pictures * args.folder_copies} pictures in {seconds:.2f} s)"
                    elif name == "first":
                        value = statistics.median(first_line(source, picture, cache) for _ in range(3))
                    else:  # cold: a mesh this machine has not loaded before (an empty load cache each time)
                        value = statistics.median(first_line(source, picture, Path(tempfile.mkdtemp(dir=work)))
                                                  for _ in range(3))
                    values[(name, code)].append(value)
                    print(f"  {name:8s} {code:4s} {value:9.2f}{total}  (load {load_average():.2f})", flush=True)
    units = {"picture": ("picture_ms", "ms, median a picture"), "folder": ("folder_per_s", "pictures/s"),
             "first": ("first_line_s", "s to the first line"),
             "cold": ("first_line_cold_s", "s to the first line, a mesh not met before")}
    line = []
    for name in figures:
        ref, tree = (statistics.median(values[(name, code)]) for code in ("ref", "tree"))
        best = max if name == "folder" else min  # a process runs fast or slow as a whole on some machines
        ref_best, tree_best = (best(values[(name, code)]) for code in ("ref", "tree"))
        key, unit = units[name]
        print(f"{key}: ref {ref:.2f}, tree {tree:.2f} {unit}; tree / ref {tree / ref:.3f} "
              f"(best round: ref {ref_best:.2f}, tree {tree_best:.2f})")
        line += [f"{key}={tree:.2f}", f"{key}_xref={tree / ref:.3f}", f"{key}_best={tree_best:.2f}",
                 f"{key}_best_xref={tree_best / ref_best:.3f}"]
    if "ref" in results and "tree" in results:
        same = sum(results["ref"][k][0] == results["tree"][k][0] and results["ref"][k][2] == results["tree"][k][2]
                   for k in results["ref"])
        worst = max(abs(results["ref"][k][1] - results["tree"][k][1]) / max(results["ref"][k][1], 1e-300)
                    for k in results["ref"])
        read = sum(r[2] == "ab42" for r in results["tree"].values())
        print(f"pictures read alike (bits, message): {same}/{len(results['ref'])}; largest relative p-value "
              f"change {worst:.2e}; message read by this tree {read}/{len(results['tree'])}")
        line.append(f"same={same}/{len(results['ref'])}")
    print(" ".join(line + [f"load={'/'.join(f'{v:.1f}' for v in loads)}"]))


if __name__ == "__main__":
    main()
