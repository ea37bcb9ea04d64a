"""Speed beside other jobs (issue #46): each figure quiet and beside competing jobs, for this tree's code
and a reference commit, in one run.

Figures (each measured in a fresh child process, `python benchmarks/contention.py --child NAME`, which
applies the code's thread policy, `meshseal.threads.configure()`, where the code has one, as the command
line does; a code without one runs with the libraries' defaults):

- `render`: our renderer, forward + backward of 4 meshes of about 5000 faces at 256x256 (benchmarks/render.py's
  batch), median of 10 after 3 warm-ups, ms;
- `detect`: a 256^2 picture of the marked bunny with its camera known (`Watermarker.read` + `decide`),
  median of 10 after 2 warm-ups, the renderer's kernels loaded first (the steady state), ms;
- `registered`: 256^2 pictures of the five textured fixtures, marked, one seeded view each, saved as 8-bit
  PNGs without metadata (`read` with registration, `look_again`, `decide`, as `meshseal detect` reads
  them): the median over the pictures after one warm-up, ms; the child also says how many read the message;
- `cli_help`: the wall time of `meshseal --help` (`python -m meshseal.cli`), median of 3, s;
- `cli_first`: the wall time from starting `meshseal detect PICTURE --mesh MESH` on one camera-known picture
  to its first result line, median of 2, s.

Conditions: `quiet` (nothing started by the benchmark; the load average printed beside it says what else
ran), `busy` (one `python -c "while True: pass"`), `batch` (another `meshseal detect` of a folder of
camera-known pictures, over and over), `blender` (a Cycles render through `meshseal render --engine
cycles`, over and over; skipped where bpy is not installed) and `load2x` (busy loops, twice the cores).
Competitors are started in their own process group and killed (by that group's id) when the condition
ends, also on errors and Ctrl-C.

The reference is `--ref COMMIT` (default HEAD~1), exported with `git archive` into a temporary folder and
put first on PYTHONPATH; this tree's `src` is the other code. Each code is warmed once first (numba
compiles its kernels into its own cache). Within a condition the two codes alternate figure by figure.

Run: python benchmarks/contention.py [--ref COMMIT] [--conditions quiet,busy,batch,blender,load2x]
                                     [--figures render,detect,registered,cli_help,cli_first] [--idle-policy]

The policy counts the cores other jobs leave free when a process starts, and the benchmark's own work
keeps about one core busy, so its children mostly take one thread. `--idle-policy` gives each child the
count the policy gives a process started on an idle machine (all the cores): its `quiet` figures are then
a user's on an idle machine, and the other conditions show such a process when a competitor starts after it.
The table gives each figure and its ratio to the same code's quiet value (x quiet), and the ratio of
this tree's code to the reference (x ref). LAST line: `NAME_CONDITION=value` for this tree's code,
`NAME_CONDITION_xquiet=ratio` and `NAME_CONDITION_xref=ratio`, and `load_CONDITION=` the one-minute load
average when the condition began.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "tests" / "fixtures"
TEXTURED = ("bunny.glb", "suzanne.glb", "teapot/teapot.obj", "sh3d_crate/crate.obj", "sh3d_deckChair/deckChair.obj")
FIGURES = ("render", "detect", "registered", "cli_help", "cli_first")
CONDITIONS = ("quiet", "busy", "batch", "blender", "load2x")
MESSAGE = "ab42"
IDLE_POLICY = "CONTENTION_IDLE_POLICY"


# ---------------------------------------------------------------- children: one figure each, one JSON line

def _policy() -> str:
    try:
        import meshseal.threads as threads
    except ImportError:
        return "library defaults"
    if os.environ.get(IDLE_POLICY):  # the count the policy takes on an idle machine (`--idle-policy`)
        threads.busy_cores = lambda: 0.0
    return f"meshseal.threads: {threads.configure()} thread(s)"


def child_render(work: Path) -> dict:
    policy = _policy()
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import torch

    from render import build_batch, median_ms

    from meshseal.render import MeshBatch, MeshRenderer, sample_seed_cameras, sample_seed_lights

    positions, normals, uvs, faces, textures, _ = build_batch()
    generator = torch.Generator().manual_seed(0)
    cameras, lights = sample_seed_cameras(4, generator), sample_seed_lights(4, generator)
    renderer = MeshRenderer(blend="splat")
    leaves = [t.clone().requires_grad_() for t in (positions, normals, uvs, textures)]

    def forward_backward():
        for leaf in leaves:
            leaf.grad = None
        p, n, u, t = leaves
        renderer(MeshBatch.from_tensors(p, n, u, faces, t), cameras, lights, 256, 256).rgba.sum().backward()

    median, _ = median_ms(forward_backward, 10)
    return {"value": median, "policy": policy}


def _watermarker():
    import meshseal

    watermarker = meshseal.load()
    return watermarker, watermarker.original(str(FIXTURES / "bunny.glb"))


def _steady() -> None:
    """The renderer's compiled kernels loaded first where the code loads them only when they pay
    (`meshseal.render.compiled`): the per-picture figures are the steady state; start-up is `cli_first`'s."""
    try:
        from meshseal.render import compiled
    except ImportError:
        return
    compiled.load()


def child_detect(work: Path) -> dict:
    policy = _policy()
    watermarker, original = _watermarker()
    _steady()
    picture = str(work / "known" / "bunny_0.png")
    times = []
    for k in range(12):
        start = time.perf_counter()
        result = watermarker.decide([watermarker.read(picture, original)])
        if k >= 2:
            times.append((time.perf_counter() - start) * 1e3)
    return {"value": statistics.median(times), "policy": policy, "read": result.message == MESSAGE}


def child_registered(work: Path) -> dict:
    policy = _policy()
    import meshseal

    watermarker = meshseal.load()
    times, right = [], 0
    for k, name in enumerate(TEXTURED):
        original = watermarker.original(str(FIXTURES / name))
        picture = str(work / "bare" / f"{k}.png")

        def one():
            reading = watermarker.read(picture, original, register=True)
            return watermarker.decide([watermarker.look_again(reading, original, None, None, True)])

        if k == 0:
            one()  # warm-up
        start = time.perf_counter()
        result = one()
        times.append((time.perf_counter() - start) * 1e3)
        right += result.message == MESSAGE
    return {"value": statistics.median(times), "max": max(times), "read": f"{right}/{len(TEXTURED)}",
            "policy": policy}


def child_cli_help(work: Path) -> dict:
    times = []
    for _ in range(3):
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "meshseal.cli", "--help"], check=True, capture_output=True)
        times.append(time.perf_counter() - start)
    return {"value": statistics.median(times)}


def child_cli_first(work: Path) -> dict:
    times = []
    for _ in range(2):
        start = time.perf_counter()
        process = subprocess.Popen([sys.executable, "-m", "meshseal.cli", "detect", str(work / "known" / "bunny_0.png"),
                                    "--mesh", str(FIXTURES / "bunny.glb")], stdout=subprocess.PIPE,
                                   stderr=subprocess.DEVNULL, text=True)
        line = process.stdout.readline()
        times.append(time.perf_counter() - start)
        process.wait()
    return {"value": statistics.median(times), "line": line.strip()}


# ---------------------------------------------------------------- the parent

def prepare(work: Path) -> None:
    """The pictures, made once with this tree's code: camera-known 256^2 views of the marked bunny (and a
    folder of them for the `batch` competitor), and one metadata-free 256^2 view of each marked fixture."""
    import numpy as np
    import torch
    from PIL import Image

    import meshseal
    from meshseal.mesh import load, normalize, to_z_up
    from meshseal.render import MeshRenderer, lights_at, sample_seed_cameras

    cli = [sys.executable, "-m", "meshseal.cli"]
    (work / "known").mkdir()
    (work / "bare").mkdir()
    marked = work / "bunny_marked.glb"
    subprocess.run(cli + ["embed", str(FIXTURES / "bunny.glb"), "-o", str(marked), "--message", MESSAGE, "--views", "0"],
                   check=True, capture_output=True)
    subprocess.run(cli + ["render", str(marked), "-o", str(work / "known" / "bunny.png"), "--width", "256",
                          "--height", "256", "--views", "8", "--seed", "3"], check=True, capture_output=True)
    watermarker = meshseal.load()
    for k, name in enumerate(TEXTURED):
        mesh = load(FIXTURES / name)
        picture = normalize(to_z_up(watermarker.embed(mesh, message=MESSAGE)))
        camera = sample_seed_cameras(1, torch.Generator().manual_seed(k))
        rgba = MeshRenderer().render(picture, camera, lights_at(torch.tensor([[2.0, 1.0, 2.0]])), 256, 256)
        Image.fromarray((rgba[0, ..., :3].clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)).save(work / "bare" / f"{k}.png")


def competitors(condition: str, work: Path) -> list[subprocess.Popen]:
    spin = [sys.executable, "-c", "while True: pass"]
    cores = len(os.sched_getaffinity(0))
    cli = f"{sys.executable} -m meshseal.cli"
    if condition == "busy":
        commands = [spin]
    elif condition == "load2x":
        commands = [spin] * (2 * cores)
    elif condition == "batch":
        commands = [["bash", "-c", f"while true; do {cli} detect {work / 'known'} --mesh {FIXTURES / 'bunny.glb'} "
                                   ">/dev/null 2>&1; done"]]
    elif condition == "blender":
        commands = [["bash", "-c", f"while true; do {cli} render {work / 'bunny_marked.glb'} -o {work / 'cycles.png'} "
                                   "--engine cycles --samples 64 >/dev/null 2>&1; done"]]
    else:
        commands = []
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    return [subprocess.Popen(c, start_new_session=True, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            for c in commands]


def stop(processes: list[subprocess.Popen]) -> None:
    for process in processes:
        try:
            os.killpg(process.pid, signal.SIGKILL)  # its own group: the loop and what it started
        except ProcessLookupError:
            pass
        process.wait()


def run_child(figure: str, source: Path, work: Path, idle_policy: bool = False) -> dict:
    env = dict(os.environ, PYTHONPATH=str(source))
    env.pop(IDLE_POLICY, None)
    if idle_policy:
        env[IDLE_POLICY] = "1"
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS", "MESHSEAL_THREADS", "OMP_WAIT_POLICY"):
        env.pop(name, None)  # each code chooses its own threads, as it would for a user
    out = subprocess.run([sys.executable, __file__, "--child", figure, "--work", str(work)], env=env,
                         capture_output=True, text=True, timeout=1800)
    if out.returncode != 0:
        raise SystemExit(f"{figure} ({source}) failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--ref", default="HEAD~1", help="reference commit (default HEAD~1; none: this tree only)")
    parser.add_argument("--conditions", default=",".join(CONDITIONS))
    parser.add_argument("--figures", default=",".join(FIGURES))
    parser.add_argument("--idle-policy", action="store_true",
                        help="children take the threads the policy gives a process started on an idle machine "
                             "(all its cores) instead of reading the load, which this benchmark's own work raises")
    parser.add_argument("--child", choices=FIGURES, help=argparse.SUPPRESS)
    parser.add_argument("--work", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(globals()[f"child_{args.child}"](args.work)))
        return
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # `timeout` or kill: the competitors still end
    figures = [f for f in args.figures.split(",") if f]
    conditions = [c for c in args.conditions.split(",") if c]
    if "blender" in conditions and importlib.util.find_spec("bpy") is None:
        print("blender: skipped (bpy is not installed)")
        conditions.remove("blender")
    if "quiet" not in conditions:
        conditions.insert(0, "quiet")
    ref = None if args.ref == "none" else subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short", args.ref], check=True, capture_output=True, text=True).stdout.strip()
    results: dict = {}
    loads: dict = {}
    with tempfile.TemporaryDirectory() as folder:
        work, ref_root = Path(folder) / "work", Path(folder) / "ref"
        work.mkdir()
        ref_root.mkdir()
        codes = {"this tree": ROOT / "src"}
        if ref is not None:
            archive = subprocess.run(["git", "-C", str(ROOT), "archive", ref, "src"], check=True,
                                     capture_output=True).stdout
            subprocess.run(["tar", "-x", "-C", str(ref_root)], input=archive, check=True)
            codes = {f"ref {ref}": ref_root / "src"} | codes
        print(f"{len(os.sched_getaffinity(0))} cores; load average at start {os.getloadavg()}; preparing pictures")
        prepare(work)
        for code, source in codes.items():  # warm-up: numba compiles into each code's own cache
            run_child("detect", source, work)
        for condition in conditions:
            processes = competitors(condition, work)
            try:
                time.sleep(2.0 if processes else 0.0)
                loads[condition] = os.getloadavg()[0]
                print(f"{condition}: {len(processes)} competitor process(es), load average {loads[condition]:.2f}",
                      flush=True)
                for figure in figures:
                    for code, source in codes.items():
                        result = run_child(figure, source, work, args.idle_policy)
                        results[(figure, condition, code)] = result
                        extra = {k: v for k, v in result.items() if k != "value"}
                        print(f"  {figure:<10} {code:<12} {result['value']:10.3f}  {extra}  "
                              f"(load {os.getloadavg()[0]:.2f})", flush=True)
            finally:
                stop(processes)
    report(results, loads, figures, conditions, list(codes))


def report(results, loads, figures, conditions, codes) -> None:
    units = {"render": "ms", "detect": "ms", "registered": "ms", "cli_help": "s", "cli_first": "s"}
    print()
    print("| figure | code | " + " | ".join(f"{c} (load {loads[c]:.1f})" for c in conditions) + " |")
    print("|---|---|" + "---|" * len(conditions))
    pairs = []
    new, ref = codes[-1], (codes[0] if len(codes) > 1 else None)
    for figure in figures:
        for code in codes:
            quiet = results[(figure, "quiet", code)]["value"]
            cells = []
            for condition in conditions:
                value = results[(figure, condition, code)]["value"]
                cell = f"{value:.3g} {units[figure]}"
                if condition != "quiet":
                    cell += f" ({value / quiet:.2f}x quiet)"
                if code == new:
                    pairs.append(f"{figure}_{condition}={value:.4g}")
                    if ref is not None:
                        ratio = value / results[(figure, condition, ref)]["value"]
                        cell += f", {ratio:.2f}x ref"
                        pairs.append(f"{figure}_{condition}_xref={ratio:.3f}")
                    if condition != "quiet":
                        pairs.append(f"{figure}_{condition}_xquiet={value / quiet:.3f}")
                cells.append(cell)
            print(f"| {figure} | {code} | " + " | ".join(cells) + " |")
    pairs += [f"load_{c}={loads[c]:.2f}" for c in conditions]
    print()
    print(" ".join(pairs))


if __name__ == "__main__":
    main()
