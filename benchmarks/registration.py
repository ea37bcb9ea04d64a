"""Registered detection per picture (issue #46): the time `meshseal detect --mesh` takes to read a 256^2
picture without metadata (registration, reading, second look, decision) and what it reads, for this tree
and a reference code in one run, picture by picture on the same pictures.

Pictures (made once with this tree's code into `--work`, reused by later runs with the same folder):

- `test`: the first `--meshes` test meshes of a built dataset (`--data`), each marked by the shipped
  default model at strength 1 with an error-corrected random ID, rendered by our renderer from one seeded
  view of the seed paper's range under its light range over a plain random background, 256^2, saved as an
  8-bit PNG without metadata (as `experiments/registration_conditions.py --conditions plain` makes them);
- `fixture`: the five textured fixtures (bunny, suzanne, teapot, crate, deck chair) marked with "ab42"
  through `Watermarker.embed`, two seeded views each of the seed's camera range, light (2, 1, 2), black
  background, 256^2 8-bit PNG (as `benchmarks/embed_detect.py` makes them).

Each code runs in its own long-lived worker process (`--child`, its `src` first on PYTHONPATH,
`meshseal.threads.configure()` applied, `OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1` unless set), warmed on
one picture first; the original mesh is prepared once per mesh outside the timed part (as `meshseal detect`
prepares it once for a folder). Pictures are sent to the two workers one after the other, the order
alternating picture by picture, so that both see the same load. Timed per picture: `Watermarker.read(...,
register=True)`, `look_again`, `decide`, as `meshseal detect` runs them.

Printed per code: the per-picture seconds (median, p90, p99, max) over all pictures and per kind, of
them the seconds inside registration (`register_with_masks`, the camera search alone), the CPU seconds
of the worker process (`time.process_time`: less moved by other jobs than the wall clock), the
registered bit accuracy (decided bits against the embedded ones), the detection rate at FPR 1e-6, the
exact-message rate, registration success (pose error < 0.5 px or silhouette IoU >= 0.95) and the median
pose error; then the pictures whose bits differ between the codes. `uptime` at start and end. Last line:
`key=value` pairs (this tree, and `ref_` for the reference; `speedup` = ref median / tree median).

    python benchmarks/registration.py --data data --meshes 100 [--ref /tmp/regref|COMMIT|none]
                                      [--work /tmp/regbench] [--fixture-views 2] [--jsonl rows.jsonl]
                                      [--subdivide K --roughen A] [--unrelated K]

`--subdivide` and `--roughen` make the test meshes high-poly (`test_mesh`; pictures in their own
`--work`); `--unrelated K` reads each test picture against test mesh (its own + K) instead, as a scan of
many pictures for one asset mostly meets them (its "detected" column is then the false-positive rate).
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "tests" / "fixtures"
TEXTURED = ("bunny.glb", "suzanne.glb", "teapot/teapot.obj", "sh3d_crate/crate.obj", "sh3d_deckChair/deckChair.obj")
MESSAGE = "ab42"
SIZE = 256


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


# ---------------------------------------------------------------- pictures

def test_mesh(dataset, index: int, subdivide: int = 0, roughen: float = 0.0) -> dict:
    """Test mesh `index` as `collate` gives it, or, with `subdivide`, its faces each cut into four
    (edge midpoints; normals, UVs interpolated) that many times, a high-poly asset of the same look;
    `roughen` then moves every vertex out from the centre by up to that share of the mesh's size, a
    function of its position alone (seam copies stay together): detail finer than a pixel of the
    search's silhouettes, as a scan has, which a decimated outline cannot keep exactly."""
    import torch

    from meshseal.data.dataset import collate
    from meshseal.mesh.preprocess import subdivide as subdivide_mesh

    batch = collate([dataset[index]], "cpu")
    if not subdivide and not roughen:
        return batch
    n_verts, n_faces = int(batch["n_verts"][0]), int(batch["n_faces"][0])
    positions, normals = batch["positions"][0, :n_verts], batch["normals"][0, :n_verts]
    uvs, faces = batch["uvs"][0, :n_verts], batch["faces"][0, :n_faces]
    positions, normals, uvs, faces = subdivide_mesh(positions, normals, uvs, faces, subdivide)
    if roughen:
        centre = positions.mean(0)
        size = float((positions.amax(0) - positions.amin(0)).norm())
        k = 2 * torch.pi * 40 / size  # forty waves across the mesh
        bump = torch.sin(k * positions[:, 0]) * torch.sin(k * 1.3 * positions[:, 1]) * torch.sin(k * 0.7 * positions[:, 2])
        positions = positions + roughen * size * bump[:, None] * torch.nn.functional.normalize(positions - centre, dim=1)
    return batch | {"positions": positions[None], "normals": normals[None], "uvs": uvs[None], "faces": faces[None],
                    "n_verts": torch.tensor([len(positions)]), "n_faces": torch.tensor([len(faces)])}


def prepare(work: Path, data: Path, meshes: int, fixture_views: int, subdivide: int = 0, roughen: float = 0.0) -> list[dict]:
    """The pictures and what each carries (index.json in `work`), made once."""
    index_path = work / "index.json"
    if index_path.exists():
        items = json.loads(index_path.read_text())
        made = {(item.get("subdivide", 0), item.get("roughen", 0.0)) for item in items if item["kind"] == "test"}
        if made and made != {(subdivide, roughen)}:
            sys.exit(f"registration.py: {work} holds pictures of other meshes (--subdivide, --roughen {sorted(made)[0]}): "
                     "give another --work")
        have_test = sum(item["kind"] == "test" for item in items)
        have_fixture = sum(item["kind"] == "fixture" for item in items)
        if have_test >= meshes and have_fixture == len(TEXTURED) * fixture_views:
            tests = [item for item in items if item["kind"] == "test"][:meshes]
            return tests + [item for item in items if item["kind"] == "fixture"]
    import numpy as np
    import torch
    from PIL import Image

    import meshseal
    from meshseal import payload
    from meshseal.data.dataset import MeshDataset
    from meshseal.mesh import load, normalize, to_z_up
    from meshseal.methods.batches import batch_mark_grid, batch_texels_used
    from meshseal.render import MeshBatch, MeshRenderer, lights_at, sample_seed_cameras
    from meshseal.render.views import sample_views
    from meshseal.training.views import random_backgrounds

    work.mkdir(parents=True, exist_ok=True)
    watermarker = meshseal.load()
    model = watermarker.model
    renderer = MeshRenderer()
    items = []

    def save(array, name: str) -> str:
        path = work / name
        Image.fromarray((array.clamp(0, 1).permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)).save(path)
        return str(path)

    def camera_of(cameras) -> dict:
        return {"eye": cameras.eye[0].tolist(), "at": cameras.at[0].tolist(), "up": cameras.up[0].tolist(),
                "fov_y": float(cameras.fov_y), "principal": [float(v) for v in cameras.principal]}

    dataset = MeshDataset(data, "test")
    for index in range(min(meshes, len(dataset))):
        batch = test_mesh(dataset, index, subdivide, roughen)
        positions, normals, uvs, faces, texture = (batch[k] for k in ("positions", "normals", "uvs", "faces", "texture"))
        generator = torch.Generator().manual_seed(index)
        identity = int(torch.randint(0, 2 ** 31, (1,), generator=generator))
        message = payload.encode(identity, None, model.n_bits)[None]
        with torch.no_grad():
            marked = model.texture_encoder(texture, message, 1.0, payload.key_seed(None),
                                           batch_mark_grid(model.texture_encoder, batch), batch_texels_used(batch))
            cameras, lights = sample_views(1, "seed", generator)
            background = random_backgrounds(1, generator)
            out = renderer(MeshBatch.from_tensors(positions, normals, uvs, faces, marked), cameras, lights, SIZE, SIZE,
                           background)
        items.append({"kind": "test", "mesh": index, "picture": save(out.image[0], f"test_{index:03d}.png"),
                      "bits": [int(b) for b in message[0]], "message": identity, "camera": camera_of(cameras),
                      "subdivide": subdivide, "roughen": roughen, "faces": int(batch["n_faces"][0])})
    for k, name in enumerate(TEXTURED):
        mesh = load(FIXTURES / name)
        picture = normalize(to_z_up(watermarker.embed(mesh, message=MESSAGE)))
        bits = [int(b) for b in payload.encode(MESSAGE, None, model.n_bits)]
        for view in range(fixture_views):
            camera = sample_seed_cameras(1, torch.Generator().manual_seed(10 * k + view))
            with torch.no_grad():
                rgba = MeshRenderer().render(picture, camera, lights_at(torch.tensor([[2.0, 1.0, 2.0]])), SIZE, SIZE)
            items.append({"kind": "fixture", "mesh": name, "picture": save(rgba[0, ..., :3].permute(2, 0, 1),
                                                                         f"fixture_{k}_{view}.png"),
                          "bits": bits, "message": MESSAGE, "camera": camera_of(camera)})
    index_path.write_text(json.dumps(items))
    return items


# ---------------------------------------------------------------- the worker (one per code)

def child(data: Path, settings: list[str]) -> None:
    """Reads picture items (JSON lines on stdin), answers one JSON line each on stdout. `settings`:
    MODULE.NAME=VALUE (e.g. meshseal.reading.registration.FLAT_ENOUGH=0, or a tuple:
    ...TEXTURE_SIGMAS=4,2,1), set after import."""
    try:
        from meshseal.threads import configure

        configure()
    except ImportError:
        pass
    import numpy as np
    import torch

    import meshseal
    from meshseal.data.dataset import MeshDataset
    from meshseal.reading.registration import pose_error
    from meshseal.render import Cameras, MeshBatch

    import importlib

    for setting in settings:
        name, value = setting.split("=", 1)
        module, attribute = name.rsplit(".", 1)
        target = importlib.import_module(module)
        current = getattr(target, attribute)
        given = ast.literal_eval(value)
        setattr(target, attribute, tuple(float(v) for v in given) if isinstance(current, tuple) else type(current)(given))
    from meshseal.reading import registration

    spent = [0.0]  # seconds inside registration (`register_with_masks`) for the picture being read
    register_with_masks = registration.register_with_masks

    def timed(*args, **kwargs):
        started = time.perf_counter()
        try:
            return register_with_masks(*args, **kwargs)
        finally:
            spent[0] += time.perf_counter() - started

    registration.register_with_masks = timed  # read.py imports it at call time, from the module
    watermarker = meshseal.load()
    dataset = MeshDataset(data, "test")
    originals = {}

    def original_of(item):
        mesh = item.get("original", item["mesh"])  # `--unrelated`: another mesh's original
        key = (item["kind"], mesh)
        if key not in originals:
            if item["kind"] == "test":
                batch = test_mesh(dataset, mesh, item.get("subdivide", 0), item.get("roughen", 0.0))
                originals[key] = MeshBatch.from_tensors(*(batch[k] for k in ("positions", "normals", "uvs", "faces",
                                                                               "texture")))
            else:
                originals[key] = watermarker.original(str(FIXTURES / item["mesh"]))
        return originals[key]

    print(json.dumps({"ready": True, "torch_threads": torch.get_num_threads()}), flush=True)
    for line in sys.stdin:
        item = json.loads(line)
        original = original_of(item)
        started, cpu, spent[0] = time.perf_counter(), time.process_time(), 0.0
        try:
            reading = watermarker.read(item["picture"], original, register=True)
            reading = watermarker.look_again(reading, original, None, None, True)
            found = watermarker.decide([reading])
        except meshseal.MeshsealError:
            reading = found = None
        seconds, cpu = time.perf_counter() - started, time.process_time() - cpu
        if found is None:
            row = {"seconds": seconds, "cpu": cpu, "registration": spent[0], "bit_acc": 0.5, "detected": False, "exact": False, "pose": float("inf"),
                   "iou": 0.0, "bits": None}
        else:
            got = [int(b) for b in found.bits]
            c = item["camera"]
            truth = Cameras(torch.tensor([c["eye"]]), torch.tensor([c["at"]]), torch.tensor([c["up"]]), c["fov_y"],
                            principal=tuple(c["principal"]))
            pose = pose_error(original, truth, reading.found, SIZE, SIZE) if "original" not in item else float("nan")
            row = {"seconds": seconds, "cpu": cpu, "registration": spent[0], "bit_acc": float(np.mean(np.array(got) == np.array(item["bits"]))),
                   "detected": bool(found.detected), "exact": found.message == item["message"], "pose": pose,
                   "iou": float(reading.registration_iou or 0.0), "bits": "".join(map(str, got))}
        print(json.dumps(row), flush=True)


class Worker:
    def __init__(self, name: str, src: Path, data: Path, settings: list[str] = ()):
        env = dict(os.environ)
        env.setdefault("OMP_NUM_THREADS", "1")
        env.setdefault("NUMBA_NUM_THREADS", "1")
        env["PYTHONPATH"] = str(src) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        self.name = name
        self.process = subprocess.Popen([sys.executable, __file__, "--child", "--data", str(data),
                                         *(f"--set={s}" for s in settings)], env=env,
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=str(ROOT))
        self.hello = json.loads(self.process.stdout.readline())

    def __call__(self, item: dict) -> dict:
        self.process.stdin.write(json.dumps(item) + "\n")
        self.process.stdin.flush()
        line = self.process.stdout.readline()
        if not line:
            raise RuntimeError(f"worker {self.name} ended")
        return json.loads(line)

    def close(self):
        self.process.stdin.close()
        self.process.wait()


def percentile(values: list[float], q: float) -> float:
    import numpy as np

    return float(np.percentile(np.asarray(values), q)) if values else float("nan")


def summary(rows: list[dict]) -> dict:
    import numpy as np

    seconds, cpu = [r["seconds"] for r in rows], [r["cpu"] for r in rows]
    return {"n": len(rows), "median_s": percentile(seconds, 50), "p90_s": percentile(seconds, 90),
            "p99_s": percentile(seconds, 99), "max_s": max(seconds), "mean_s": float(np.mean(seconds)),
            "registration_median_s": percentile([r["registration"] for r in rows], 50),
            "cpu_median_s": percentile(cpu, 50), "cpu_p90_s": percentile(cpu, 90), "cpu_p99_s": percentile(cpu, 99),
            "bit_acc": float(np.mean([r["bit_acc"] for r in rows])),
            "detected": float(np.mean([r["detected"] for r in rows])),
            "exact": float(np.mean([r["exact"] for r in rows])),
            "success": float(np.mean([(r["pose"] < 0.5) or (r["iou"] >= 0.95) for r in rows])),
            "pose_median": float(np.median([r["pose"] for r in rows]))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT / "data")
    parser.add_argument("--meshes", type=int, default=100)
    parser.add_argument("--fixture-views", type=int, default=2)
    parser.add_argument("--subdivide", type=int, default=0,
                        help="each test mesh's faces cut in four this many times (5,000 faces -> 80,000 at 2)")
    parser.add_argument("--unrelated", type=int, default=0, metavar="K",
                        help="read each test picture against test mesh (its own + K) instead, no fixtures: a scan of "
                             "pictures that do not show the mesh (its detected column is the false-positive rate)")
    parser.add_argument("--roughen", type=float, default=0.0,
                        help="then its vertices moved by up to this share of its size (detail finer than the search's pixels)")
    parser.add_argument("--ref", default="/tmp/regref", help="a source tree (with src/), a commit, or none")
    parser.add_argument("--tree-src", type=Path, default=ROOT / "src",
                        help="this tree's code (a snapshot of src/ to go on editing while it runs)")
    parser.add_argument("--work", type=Path, default=None, help="folder for the pictures (kept, reused)")
    parser.add_argument("--jsonl", type=Path, default=None, help="one JSON line per picture and code")
    parser.add_argument("--set", action="append", default=[], metavar="MODULE.NAME=VALUE",
                        help="a module constant set in this tree's worker (an option's other value)")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.data, args.set)
        return
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")
    print(f"start: {uptime()}", flush=True)
    work = args.work or Path(tempfile.mkdtemp(prefix="regbench_"))
    sys.path.insert(0, str(ROOT / "src"))
    items = prepare(work, args.data, args.meshes, args.fixture_views, args.subdivide, args.roughen)
    if args.unrelated:
        tests = [item for item in items if item["kind"] == "test"]
        items = [item | {"original": tests[(k + args.unrelated) % len(tests)]["mesh"]} for k, item in enumerate(tests)]
    print(f"{len(items)} pictures in {work}", flush=True)
    codes = [("tree", args.tree_src)]
    if args.ref != "none":
        ref = Path(args.ref)
        if not (ref / "src").is_dir():
            exported = Path(tempfile.mkdtemp(prefix="regref_"))
            subprocess.run(f"git -C {ROOT} archive {args.ref} src | tar -x -C {exported}", shell=True, check=True)
            ref = exported
        label = subprocess.run(["git", "-C", str(ref), "rev-parse", "--short", "HEAD"], capture_output=True,
                               text=True).stdout.strip() or args.ref
        codes.insert(0, (f"ref {label}", ref / "src"))
    workers = [Worker(name, src, args.data, args.set if name == "tree" else ()) for name, src in codes]
    if args.set:
        print(f"tree worker settings: {' '.join(args.set)}")
    for worker in workers:  # warm-up: numba's kernels, the model, first-call costs
        worker(items[0])
    rows = {w.name: [] for w in workers}
    log = args.jsonl.open("w") if args.jsonl else None
    try:
        for number, item in enumerate(items):
            order = workers if number % 2 == 0 else workers[::-1]
            line = []
            for worker in order:
                row = worker(item) | {"kind": item["kind"], "mesh": item["mesh"], "picture": Path(item["picture"]).name}
                rows[worker.name].append(row)
                line.append(f"{worker.name}: {row['seconds']:.2f} s ({row['cpu']:.2f} CPU) bits {row['bit_acc']:.3f}"
                            f"{' det' if row['detected'] else ''}")
                if log:
                    log.write(json.dumps(row | {"code": worker.name}) + "\n")
                    log.flush()
            print(f"{number + 1}/{len(items)} {Path(item['picture']).name}: " + " | ".join(line), flush=True)
    finally:
        for worker in workers:
            worker.close()
    print(f"end: {uptime()}")
    print("| code | pictures | median s | p90 s | p99 s | max s | mean s | registration median s | CPU median / p90 / p99 s | "
          "bit acc. | detected | exact | reg. success | median pose px |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    results = {}
    for name, group in rows.items():
        for kind in ("all", "test", "fixture"):
            chosen = [r for r in group if kind == "all" or r["kind"] == kind]
            if not chosen:
                continue
            s = summary(chosen)
            results[(name, kind)] = s
            print(f"| {name} ({kind}) | {s['n']} | {s['median_s']:.2f} | {s['p90_s']:.2f} | {s['p99_s']:.2f} | "
                  f"{s['max_s']:.2f} | {s['mean_s']:.2f} | {s['registration_median_s']:.2f} | {s['cpu_median_s']:.2f} / {s['cpu_p90_s']:.2f} / "
                  f"{s['cpu_p99_s']:.2f} | {s['bit_acc']:.4f} | {s['detected']:.3f} | "
                  f"{s['exact']:.3f} | {s['success']:.3f} | {s['pose_median']:.3f} |")
    tree = results[("tree", "all")]
    pairs = {}
    if len(workers) == 2:
        ref_rows, tree_rows = rows[workers[0].name], rows["tree"]
        ratios = sorted(t["seconds"] / r["seconds"] for r, t in zip(ref_rows, tree_rows))
        cpu_ratios = sorted(t["cpu"] / r["cpu"] for r, t in zip(ref_rows, tree_rows))
        differ = [(r["picture"], r["bit_acc"], t["bit_acc"], r["detected"], t["detected"])
                  for r, t in zip(ref_rows, tree_rows) if r["bits"] != t["bits"]]
        print(f"per-picture time ratio tree / ref: median {percentile(ratios, 50):.3f}, p90 {percentile(ratios, 90):.3f}; "
              f"CPU time: median {percentile(cpu_ratios, 50):.3f}, p90 {percentile(cpu_ratios, 90):.3f}")
        registration_ratios = sorted(t["registration"] / r["registration"] for r, t in zip(ref_rows, tree_rows)
                                     if r["registration"] > 0)
        print(f"per-picture registration time ratio tree / ref: median {percentile(registration_ratios, 50):.3f}")
        print(f"pictures whose decided bits differ: {len(differ)}")
        for picture, ref_acc, tree_acc, ref_det, tree_det in differ:
            print(f"  {picture}: bits ref {ref_acc:.3f} tree {tree_acc:.3f}; detected ref {ref_det} tree {tree_det}")
        ref = results[(workers[0].name, "all")]
        pairs = {f"ref_{k}": v for k, v in ref.items() if k != "n"}
        pairs["speedup"] = ref["median_s"] / tree["median_s"]
        pairs["cpu_speedup"] = ref["cpu_median_s"] / tree["cpu_median_s"]
        pairs["registration_speedup"] = ref["registration_median_s"] / tree["registration_median_s"]
        pairs["bits_differ"] = len(differ)
    load = os.getloadavg()[0]
    values = {k: v for k, v in tree.items()} | pairs | {"load": load}
    print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in values.items()))


if __name__ == "__main__":
    main()
