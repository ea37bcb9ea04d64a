"""Small objects (issue #45: "objects of 200+ pixels" must read): the five textured fixtures marked by
`meshseal embed --message ab42` (the shipped default), rendered by `meshseal render` at 256^2 from far
away (`--distances`, in units of the object's radius; seeded directions, elevation 10-50 degrees, the
command's own light and background), so that each object covers a few hundred to under two thousand
pixels. Each picture is read twice, as `meshseal detect` reads it: with its camera in the PNG's
metadata, and from a copy without metadata (registered, second look included). One JSON line per
picture (object pixels, detected and exact either way, the registered p-value, pose error against the
metadata's camera, seconds), then a table by fixture and by object size.

    python experiments/small_objects.py --work DIR [--views 4] [--distances 14 20] [--part 0/2] [--set MODULE.NAME=VALUE]
    python experiments/small_objects.py --merge DIR/part0.jsonl DIR/part1.jsonl
    python experiments/small_objects.py --work DIR --oracle

`--oracle` reads each picture with its camera only, as shipped and against the unmarked original rendered
by `meshseal render` from the same camera (the prediction no user has), and prints the mark's own size in
the picture (its changed pixels and their RMS in grey levels): whether a small object is lost to the
prediction or to the mark's energy.

The pictures are made once into `--work` (reused); `--part I/N` reads every N-th picture from the I-th
(two processes on two cores); `--set` overrides a module constant (e.g.
meshseal.reading.read.REGISTER_MIN_SIDE=0) for a side-by-side run.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import json
import math
import os
import random
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = {"bunny": "bunny.glb", "suzanne": "suzanne.glb", "teapot": "teapot/teapot.obj",
            "crate": "sh3d_crate/crate.obj", "deckChair": "sh3d_deckChair/deckChair.obj"}
MESSAGE = "ab42"
SIZES = ((0, 300), (300, 600), (600, 10 ** 9))


def cameras_of(number: int, views: int, distances: list[float]) -> list[str]:
    """The `--camera` arguments of fixture `number`'s seeded views."""
    generator = random.Random(number)
    cameras = []
    for distance in distances:
        for _ in range(views):
            azimuth, elevation = generator.uniform(0, 2 * math.pi), math.radians(generator.uniform(10, 50))
            cameras.append(f"--camera={distance * math.cos(elevation) * math.cos(azimuth):.3f},"
                           f"{distance * math.cos(elevation) * math.sin(azimuth):.3f},"
                           f"{distance * math.sin(elevation):.3f}")
    return cameras


def make_pictures(work: Path, views: int, distances: list[float]) -> list[dict]:
    """Mark each fixture and render it from far away (the command line's own files); a copy of each
    picture without metadata beside it."""
    index = work / "index.json"
    if index.exists():
        return json.loads(index.read_text())
    from PIL import Image

    work.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "meshseal.cli"]
    items = []
    for number, (name, path) in enumerate(FIXTURES.items()):
        marked = work / name / Path(path).name
        marked.parent.mkdir(exist_ok=True)
        subprocess.run([*command, "embed", str(ROOT / "tests" / "fixtures" / path), "-o", str(marked), "--message",
                        MESSAGE, "--views", "0"], check=True, capture_output=True)
        cameras = cameras_of(number, views, distances)
        subprocess.run([*command, "render", str(marked), "-o", str(work / f"{name}.png"), "--width", "256", "--height",
                        "256", *cameras], check=True, capture_output=True)
        for view in range(len(cameras)):
            picture = work / f"{name}_{view}.png"
            bare = work / f"bare_{name}_{view}.png"
            Image.open(picture).convert("RGB").save(bare)  # no metadata
            items.append({"mesh": name, "picture": str(picture), "bare": str(bare),
                          "distance": distances[view // views]})
    index.write_text(json.dumps(items))
    return items


def read(items: list[dict], settings: list[str]) -> None:
    from meshseal.threads import configure

    configure()
    import numpy as np

    import meshseal
    from meshseal.reading.pictures import camera_from_metadata, load_picture_and_codecs
    from meshseal.reading.registration import pose_error

    for setting in settings:
        name, value = setting.split("=", 1)
        module, attribute = name.rsplit(".", 1)
        target = importlib.import_module(module)
        current, given = getattr(target, attribute), ast.literal_eval(value)
        setattr(target, attribute, tuple(given) if isinstance(current, tuple) else type(current)(given))
    watermarker = meshseal.load()
    originals = {}
    for item in items:
        original = originals.setdefault(item["mesh"], watermarker.original(ROOT / "tests" / "fixtures" / FIXTURES[item["mesh"]]))
        pixels, _, text, _, _ = load_picture_and_codecs(item["picture"])
        truth = camera_from_metadata(text, "cpu", item["picture"])
        background = pixels[0, 0]
        row = {"picture": Path(item["picture"]).name, "mesh": item["mesh"],
               "pixels": int((np.abs(pixels - background).sum(-1) > 6 / 255).sum())}
        try:
            known = watermarker.decide([watermarker.read(item["picture"], original)])
            row |= {"known": bool(known.detected), "known_exact": known.message == MESSAGE}
        except meshseal.MeshsealError:
            row |= {"known": False, "known_exact": False}
        start = time.perf_counter()
        try:
            reading = watermarker.read(item["bare"], original, register=True)
            reading = watermarker.look_again(reading, original)
            found = watermarker.decide([reading])
            row |= {"registered": bool(found.detected), "registered_exact": found.message == MESSAGE,
                    "p": found.p_value, "pose": pose_error(original, truth, reading.found, *pixels.shape[:2])}
        except meshseal.MeshsealError:
            row |= {"registered": False, "registered_exact": False, "p": 1.0, "pose": float("nan")}
        row["seconds"] = round(time.perf_counter() - start, 2)
        print(json.dumps(row), flush=True)


def oracle(work: Path, items: list[dict], views: int, distances: list[float]) -> None:
    """Each picture read with its camera, as shipped and against the unmarked original's render from
    that camera (rendered once into `work`), with the mark's size in the picture; a table by size."""
    from dataclasses import replace

    import numpy as np
    import torch
    from PIL import Image

    from meshseal.threads import configure

    configure()
    import meshseal
    import meshseal.methods.spread as spread_module
    import meshseal.reading.footprint as footprint_module

    command = [sys.executable, "-m", "meshseal.cli"]
    for number, (name, path) in enumerate(FIXTURES.items()):
        if not (work / f"original_{name}_0.png").exists():
            subprocess.run([*command, "render", str(ROOT / "tests" / "fixtures" / path), "-o", str(work / f"original_{name}.png"),
                            "--width", "256", "--height", "256", *cameras_of(number, views, distances)],
                           check=True, capture_output=True)
    relit, footprint, remember = spread_module.relit_residual, spread_module.picture_footprint, footprint_module.remember_choice
    clean = {}

    def against_original(mesh, image, cameras, **options):  # the unmarked render as the prediction
        found = relit(mesh, image, cameras, **options)
        flat = torch.from_numpy(clean["picture"].astype(np.float32) / 255.0).reshape(-1, 3).to(found.expected)
        return replace(found, expected=flat.index_select(0, found.fragments.pixel.index_select(0, found.keep)))

    watermarker = meshseal.load()
    originals, rows = {}, []
    for item in items:
        original = originals.setdefault(item["mesh"], watermarker.original(ROOT / "tests" / "fixtures" / FIXTURES[item["mesh"]]))
        picture = Path(item["picture"])
        marked = np.asarray(Image.open(picture).convert("RGB"))
        clean["picture"] = np.asarray(Image.open(picture.with_name("original_" + picture.name)).convert("RGB"))
        changed = np.abs(marked.astype(np.int16) - clean["picture"].astype(np.int16)).max(-1) > 0
        difference = (marked.astype(np.float64) - clean["picture"]) ** 2
        row = {"picture": picture.name, "mesh": item["mesh"], "pixels": int((np.abs(marked.astype(np.int16) - marked[0, 0]).sum(-1) > 6).sum()),
               "mark_pixels": int(changed.sum()),
               "mark_rms": float(np.sqrt(difference.mean(-1)[changed].mean())) if changed.any() else 0.0}
        for label, patched in (("shipped", False), ("oracle", True)):
            if patched:
                spread_module.relit_residual = against_original
                spread_module.picture_footprint = lambda *a, **k: None  # the unmarked render is sampled as the picture
                footprint_module.remember_choice = lambda *a, **k: None
            try:
                found = watermarker.decide([watermarker.read(item["picture"], original)])
                row[label], row[f"{label}_p"] = bool(found.detected), float(found.p_value)
            except meshseal.MeshsealError:
                row[label], row[f"{label}_p"] = False, 1.0
            finally:
                spread_module.relit_residual, spread_module.picture_footprint = relit, footprint
                footprint_module.remember_choice = remember
        rows.append(row)
        print(json.dumps(row), flush=True)
    print("| pictures | n | camera known: detected | against the unmarked render: detected | the mark's changed pixels, median | their RMS, grey levels, median |")
    print("|---|---|---|---|---|---|")
    for low, high in ((0, 10 ** 9), *SIZES):
        group = [r for r in rows if low <= r["pixels"] < high]
        label = "all" if high == 10 ** 9 and low == 0 else (f"{low}-{high - 1} px" if high < 10 ** 9 else f"{low}+ px")
        if group:
            print(f"| {label} | {len(group)} | {sum(r['shipped'] for r in group) / len(group):.2f} | "
                  f"{sum(r['oracle'] for r in group) / len(group):.2f} | {statistics.median(r['mark_pixels'] for r in group):.0f} | "
                  f"{statistics.median(r['mark_rms'] for r in group):.2f} |")


def summary(rows: list[dict]) -> None:
    def line(label: str, group: list[dict]) -> str:
        if not group:
            return f"| {label} | 0 | | | | | |"
        share = lambda key: sum(r[key] for r in group) / len(group)  # noqa: E731
        poses = [r["pose"] for r in group if r["known"] and not math.isnan(r["pose"])]
        return (f"| {label} | {len(group)} | {share('known'):.2f} / {share('known_exact'):.2f} | "
                f"{share('registered'):.2f} / {share('registered_exact'):.2f} | "
                f"{statistics.median(poses) if poses else float('nan'):.3f} | {statistics.median(r['seconds'] for r in group):.1f} |")

    print("| pictures | n | camera known: detected / exact | registered: detected / exact | registered camera's median pose error, px (pictures detected with the camera known) | median s (registered) |")
    print("|---|---|---|---|---|---|")
    print(line("all", rows))
    for name in FIXTURES:
        print(line(name, [r for r in rows if r["mesh"] == name]))
    for low, high in SIZES:
        label = f"{low}-{high - 1} px" if high < 10 ** 9 else f"{low}+ px"
        print(line(label, [r for r in rows if low <= r["pixels"] < high]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path)
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--distances", type=float, nargs="+", default=[14.0, 20.0])
    parser.add_argument("--part", default="0/1", help="I/N: read every N-th picture from the I-th")
    parser.add_argument("--set", action="append", default=[], metavar="MODULE.NAME=VALUE")
    parser.add_argument("--merge", nargs="+", type=Path)
    parser.add_argument("--oracle", action="store_true", help="camera known only: as shipped and against the unmarked render")
    args = parser.parse_args()
    if args.merge:
        summary([json.loads(line) for path in args.merge for line in path.read_text().splitlines() if line.strip()])
        return
    if args.work is None:
        parser.error("--work is required")
    os.environ.setdefault("MESHSEAL_CACHE", str(args.work / "cache"))
    items = make_pictures(args.work, args.views, args.distances)
    if args.oracle:
        oracle(args.work, items, args.views, args.distances)
        return
    part, parts = (int(v) for v in args.part.split("/"))
    read(items[part::parts], args.set)


if __name__ == "__main__":
    main()
