"""Reading settings on other engines' pictures: each engine's picture rendered once, read under each setting.

The first N test meshes of --data are marked by the model (message: the mesh's index as 4 digits, as
`meshseal embed --message` takes it) and rendered, original and marked, by each engine from one seeded
view of the seed's ranges at 256^2 on a grey background, saved as 8-bit arrays in --cache (one .npz a
mesh, kept: a later run with other settings renders nothing; Blender's engines need `pip install
'.[blender]'`). Each marked picture is then read as `meshseal detect` reads it, with the camera known
(`--register`: without metadata, registered and looked at again), after `--attack` (as `meshseal eval
--attacks` applies it), under each value of one model setting
(`--vary KEY=V1,V2,...`, e.g. `read_affine=0,1`): per engine and value, the share detected at FPR 1e-6,
named (the owner's test of its message, `detect --expect`) and the mean bit accuracy, one Markdown row each.
With `--oracle` (camera known) each marked picture is read against the same engine's own render of the
original instead of the relit original (an oracle no user has: the engine's shading, texture filtering
and sampling, without the mark), which tells whether the mark is lost in an engine's pictures or the
prediction of them is what misfits.

    python experiments/engine_reading.py --data data --meshes 24 --engines ours cycles workbench eevee \
        --cache runs/engine_cache --vary read_affine=0,1 [--register] [--model default] [--blender KEY=VALUE ...]

`--blender` renders with a setting of Blender's renderer other than its default (into its own --cache):
what a Workbench picture's studio light, highlight, antialiasing or dither costs the reading.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

import meshseal
from meshseal import payload
from meshseal.data.dataset import MeshDataset
from meshseal.mesh import normalize, to_z_up
from meshseal.render.views import sample_views
from meshseal.training.finetune import mesh_from_item

BACKGROUND = (0.5, 0.5, 0.5)


def render_cache(wm, dataset, engines: list[str], count: int, cache: Path, blender: dict | None = None) -> None:
    """Each mesh's 8-bit pictures, original and marked, by each engine (`{engine}_o`, `{engine}_m`);
    `blender`: settings of Blender's renderer other than its defaults (`render.blender.BlenderRenderer`)."""
    from meshseal.render import make_renderer

    renderers = {}
    cache.mkdir(parents=True, exist_ok=True)
    for index in range(count):
        path = cache / f"{index}.npz"
        have = set(np.load(path).files) if path.exists() else set()
        todo = [e for e in engines if f"{e}_m" not in have]
        if not todo:
            continue
        mesh = mesh_from_item(dataset[index])
        marked = wm.embed(mesh, f"{index:04d}")
        canonical = {k: normalize(to_z_up(replace(m, source=None))) for k, m in (("o", mesh), ("m", marked))}
        cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(index))
        pictures = dict(np.load(path)) if path.exists() else {}
        for engine in todo:
            options = (blender or {}) if engine in ("cycles", "eevee", "workbench") else {}
            renderer = renderers.setdefault(engine, make_renderer(engine, **options))
            for key, m in canonical.items():
                with torch.no_grad():
                    image = renderer.render(m, cameras, lights, 256, 256, background=BACKGROUND)[0, ..., :3]
                pictures[f"{engine}_{key}"] = (image.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
        temporary = cache / f"{index}.partial.npz"
        np.savez(temporary, **pictures)
        os.replace(temporary, path)
        print(f"rendered mesh {index}: {', '.join(todo)}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--meshes", type=int, default=24)
    parser.add_argument("--engines", nargs="+", default=["ours", "cycles", "workbench", "eevee"])
    parser.add_argument("--cache", type=Path, required=True, help="folder of the rendered pictures (kept, reused)")
    parser.add_argument("--vary", required=True, metavar="KEY=V1,V2", help="a model setting and the values to read under")
    parser.add_argument("--register", action="store_true", help="read without metadata: camera registered")
    parser.add_argument("--model", default="default")
    parser.add_argument("--unmarked", action="store_true",
                        help="read the unmarked originals' pictures instead: false positives and the smallest p-value")
    parser.add_argument("--oracle", action="store_true",
                        help="read against the engine's own unmarked render (camera known)")
    parser.add_argument("--attack", default="none", help="a picture attack of `meshseal eval --attacks` (jpeg90, webp80, ...)")
    parser.add_argument("--blender", action="append", default=[], metavar="KEY=VALUE",
                        help="a setting of Blender's renderer (render.blender.BlenderRenderer), e.g. workbench_light=FLAT, "
                             "workbench_specular=0, dither=0, antialiasing=OFF; give each its own --cache")
    args = parser.parse_args()
    from meshseal.render.blender import BlenderRenderer

    blender = {}
    for setting in args.blender:
        name, _, value = setting.partition("=")
        default = getattr(BlenderRenderer, name, None)
        if default is None or name.startswith("_"):
            parser.error(f"--blender: the renderer has no setting '{name}'")
        blender[name] = value if isinstance(default, str) else (value not in ("0", "false", "False") if isinstance(default, bool)
                                                                else type(default)(value))
    from meshseal.evaluation.attacks import ATTACKS, apply

    if args.attack not in ATTACKS:
        parser.error(f"--attack: one of {', '.join(ATTACKS)}")
    key, values = args.vary.split("=", 1)
    values = [float(v) for v in values.split(",")]
    wm = meshseal.load(args.model, "cpu")
    if not hasattr(wm.model.config, key):
        parser.error(f"--vary: the model has no setting '{key}'")
    dataset = MeshDataset(args.data, "test", seed=0)
    count = min(args.meshes, len(dataset))
    render_cache(wm, dataset, args.engines, count, args.cache, blender)
    clean = {}
    if args.oracle:
        if args.register:
            parser.error("--oracle reads with the camera known")
        import meshseal.methods.spread as spread_module
        import meshseal.reading.footprint as footprint_module

        relit = spread_module.relit_residual

        def oracle_relit(mesh, image, cameras, **options):  # the engine's own unmarked render as the prediction
            found = relit(mesh, image, cameras, **options)
            flat = torch.from_numpy(clean["picture"].astype(np.float32) / 255.0).reshape(-1, 3).to(found.expected)
            return replace(found, expected=flat.index_select(0, found.fragments.pixel.index_select(0, found.keep)))

        spread_module.relit_residual = oracle_relit
        spread_module.picture_footprint = lambda *a, **k: None  # the oracle is already as the engine sampled
        footprint_module.remember_choice = lambda *a, **k: None
    tally = {(e, v): [] for e in args.engines for v in values}
    for index in range(count):
        pictures = np.load(args.cache / f"{index}.npz")
        original = wm.original(mesh_from_item(dataset[index]))
        cameras, _ = sample_views(1, "seed", torch.Generator().manual_seed(index))
        expected = payload.encode(f"{index:04d}", None, wm.n_bits).numpy()
        line = []
        for engine in args.engines:
            for value in values:
                setattr(wm.model.config, key, value)
                picture = apply(args.attack, pictures[f"{engine}_{'o' if args.unmarked else 'm'}"],
                                np.random.default_rng([index, 1]))
                clean["picture"] = pictures[f"{engine}_o"]
                try:
                    if args.register:
                        reading = wm.look_again(wm.read(picture, original, register=True), original)
                    else:
                        reading = wm.read(picture, original, camera=cameras)
                except meshseal.MeshsealError:
                    tally[(engine, value)].append((False, False, 0.5, 1.0))
                    continue
                found = wm.decide([reading])
                named = wm.decide([reading], expect=f"{index:04d}")
                bits = float(np.mean([int(b) for b in found.bits] == expected))
                tally[(engine, value)].append((bool(found.detected), bool(named.detected) and named.named is not False, bits,
                                               float(found.p_value)))
                line.append(f"{engine} {key}={value:g}: {bits:.2f}{' detected' if found.detected else ''}")
        print(f"mesh {index}: " + "; ".join(line), flush=True)
    camera = ("registered" if args.register else "camera known") + (", unmarked pictures" if args.unmarked else "") \
        + (", read against the engine's own unmarked render" if args.oracle else "")
    print(f"\n| engine | {key} | pictures | detected | named | bit accuracy | smallest p |\n|---|---|---|---|---|---|---|")
    for (engine, value), rows in tally.items():
        detected, named, bits = (np.mean([r[i] for r in rows]) for i in range(3))
        print(f"| {engine} | {value:g} | {len(rows)} | {detected:.2f} | {named:.2f} | {bits:.3f} | {min(r[3] for r in rows):.2g} |")
    print(f"\n({args.model}, first {count} test meshes, one seeded 256^2 view each, attack {args.attack}, {camera}, FPR 1e-6)")


if __name__ == "__main__":
    main()
