"""Ship a trained run as a package model: copy its weights and write the model card from measurements.

    python tools/ship_model.py --run runs/default --data data --name default

Every figure in the card is measured here, by `meshseal.evaluate` on the dataset's test split, with the
seed given, so anyone can re-run this command and get the same card.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import torch

from meshseal.methods import method_for
from meshseal.data.dataset import MeshDataset
from meshseal.training.distortions import Distortions2D, Distortions3D
from meshseal.evaluation.evaluate import evaluate_registered
from meshseal.training.validate import evaluate
from meshseal.models.io import load_model, read_metadata

WEIGHTS = Path(__file__).resolve().parents[1] / "src" / "meshseal" / "weights"


def method_lines(method) -> list[str]:
    """The card's lines that describe the weights: the method with its parameters, the architecture."""
    return [f"- Method: `{method.name}` (`meshseal.methods.{method.name}`); params: "
            + ", ".join(f"{k} {v}" for k, v in method.params().items()) + ".",
            f"- Architecture: {method.describe()}."]


def refresh_header(name: str) -> int:
    """Rewrite the Method and Architecture lines of a shipped model's card from its weights."""
    card = WEIGHTS / f"{name}.md"
    method = method_for(load_model(WEIGHTS / f"{name}.safetensors"))
    lines = [line for line in card.read_text().splitlines() if not line.startswith(("- Method:", "- Architecture:"))]
    at = next(i for i, line in enumerate(lines) if line.startswith("- Payload:")) + 1
    card.write_text("\n".join(lines[:at] + method_lines(method) + lines[at:]) + "\n")
    print(f"wrote {card}")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, help="training run folder (has model.safetensors)")
    parser.add_argument("--data", type=Path, help="dataset folder (meshseal data build)")
    parser.add_argument("--header-only", action="store_true",
                        help="rewrite only the card's Method and Architecture lines of the shipped NAME from its weights "
                             "(they describe the weights; the measured tables below stay as their command wrote them)")
    parser.add_argument("--name", default="default")
    parser.add_argument("--views", type=int, default=2, help="views per test mesh")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--size", type=int, default=256, help="render size of the test pictures (default 256)")
    parser.add_argument("--register-meshes", type=int, default=100,
                        help="informed models: test meshes for the end-to-end row with registration (slow)")
    parser.add_argument("--attacks", default=None,
                        help="informed models: the road-to-the-web table, as `meshseal eval --attacks` (comma-separated "
                             "names of meshseal.evaluation.attacks without a change of camera)")
    parser.add_argument("--attack-meshes", type=int, default=100, help="test meshes for the --attacks table")
    args = parser.parse_args()
    if args.header_only:
        return refresh_header(args.name)
    if args.run is None or args.data is None:
        parser.error("--run and --data are required (except with --header-only)")

    source = args.run / "model.safetensors"
    metadata = read_metadata(source)
    model = load_model(source)
    dataset = MeshDataset(args.data, "test", seed=args.seed)
    method = method_for(model)
    surface = method.paper_pictures  # blind, read from the seed paper's 600 x 400 pictures
    size = (400, 600) if surface else args.size
    size_text = "600 x 400 (the paper's)" if surface else f"{args.size}^2"
    rows = {}
    settings = [("seed views, no attack", "seed", None, None, 0.0, dataset),
                ("any view, no attack", "any", None, None, 0.0, dataset),
                ("seed views, 3D distortions", "seed", Distortions3D(1.0), None, 0.0, dataset),
                ("seed views, 2D attacks (strength 0.5)", "seed", None, Distortions2D(0.5), 0.0, dataset)]
    if method.informed:
        settings.append((f"seed views, camera off by ~1 px ({args.size}^2)", "seed", None, None, 1.0, dataset))
    if surface:  # the paper's protocol first (`meshseal eval --protocol seed`), then real UV atlases
        seed_items = MeshDataset(args.data, "test", seed=args.seed, texture_kinds=("noise", "real"))
        own_items = MeshDataset(args.data, "test", seed=args.seed, texture_kinds=("own",))
        settings = [("seed protocol: spherical UVs, noise or real textures, seed views", "seed", None, None, 0.0, seed_items),
                    ("own UV atlases, seed views", "seed", None, None, 0.0, own_items),
                    ("own UV atlases, any view", "any", None, None, 0.0, own_items),
                    ("seed protocol, 3D distortions", "seed", Distortions3D(1.0), None, 0.0, seed_items),
                    ("seed protocol, 2D attacks (strength 0.5)", "seed", None, Distortions2D(0.5), 0.0, seed_items)]
    for label, sampler, d3, d2, jitter, items in settings:
        torch.manual_seed(args.seed)
        rows[label] = evaluate(model, items, None, args.views, args.seed, size, sampler,
                               distortions_3d=d3, distortions_2d=d2, unrender_jitter=jitter)
        print(label, json.dumps(rows[label]), flush=True)
    registered, shipped = None, None
    if method.calibrated:
        torch.manual_seed(args.seed)  # the whole split as `meshseal embed` marks it, read with the camera known
        shipped = evaluate_registered(model, dataset, None, args.seed, args.size, "seed", views=args.views, register=False)
        print("as shipped", json.dumps(shipped), flush=True)
    if method.informed and args.register_meshes > 0:
        torch.manual_seed(args.seed)
        registered = evaluate_registered(model, dataset, args.register_meshes, args.seed, args.size, "seed")
        print("registered", json.dumps(registered), flush=True)
    attacked = None
    if method.informed and args.attacks:
        from meshseal.evaluation.attacks import parse

        torch.manual_seed(args.seed)  # marked as `meshseal embed` marks, saved, attacked, read with the camera known
        attacked = evaluate_registered(model, dataset, args.attack_meshes, args.seed, args.size, "seed", views=1,
                                       register=False, attacks=parse(args.attacks))
        print("attacks", json.dumps(attacked), flush=True)
    stats = json.loads(subprocess.run([sys.executable, "-m", "meshseal.cli", "data", "stats", str(args.data), "--json"],
                                      capture_output=True, text=True, check=True).stdout)
    WEIGHTS.mkdir(parents=True, exist_ok=True)
    target = WEIGHTS / f"{args.name}.safetensors"
    shutil.copyfile(source, target)
    config = json.loads(metadata["config"])
    train_config = json.loads(metadata.get("train_config", "{}"))
    steps = int(metadata.get("steps") or 0)
    device = metadata.get("device", "cpu")
    where = "this repository's 2-core CPU machine" if device == "cpu" else f"one {device}"
    built = (f"(seed {metadata.get('seed')}, {steps} steps, {float(metadata.get('training_seconds', 0)) / 60:.1f} min on "
             f"{where})" if steps else
             "(nothing is learned: the pattern is drawn from the config's seeds in well under a second)")
    from meshseal.payload import SCHEMAS, payload_bits

    payload = (f"{payload_bits(config['n_bits'])} payload bits after error correction and header (docs/payload.md)"
               if config["n_bits"] in SCHEMAS else "no payload schema: raw bits only")
    lines = [
        f"# Model card: `{args.name}`",
        "",
        f"- Payload: **{config['n_bits']} raw bits** ({payload}), strategy `{config['strategy']}`; file "
        f"`{target.name}` ({target.stat().st_size / 1e3:.1f} kB, safetensors).",
        *method_lines(method),
        f"- Built by: `meshseal train --config configs/{train_config.get('name', args.name)}.yaml --out {args.run}` "
        f"{built}"
        + (f", starting from the weights of `{train_config['train']['init_from']}`" if train_config.get("train", {}).get("init_from")
           else "") + ".",
        f"- Data: `meshseal data build --out {args.data}`: {stats.get('n_train')} train / {stats.get('n_test')} test "
        f"meshes, {stats.get('n_textures')} real texture images, {stats.get('n_categories')} categories "
        "(Debian packages; see the dataset's manifest for sources and licenses).",
        f"- Card written by: `python tools/ship_model.py --run {args.run} --data {args.data} --name {args.name} "
        f"--views {args.views} --size {args.size} --seed {args.seed} --register-meshes {args.register_meshes}"
        + (f" --attacks {args.attacks} --attack-meshes {args.attack_meshes}" if args.attacks else "") + "`",
        "",
        (f"## Test split ({args.views} view(s) per mesh, " if surface else
         f"## Test split ({next(iter(rows.values()))['n_meshes']} meshes x {args.views} views, ")
        + f"differentiable renderer, {size_text} renders, "
        + ("read from the picture alone, object found from the plain background)" if surface else "camera known)"),
        "",
        "| setting | bit acc | std | object PSNR (dB) | object SSIM | object FLIP | texture PSNR, shown texels (dB) | texture PSNR (dB) | frame PSNR (dB) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for label, m in rows.items():
        label = f"{label} ({m['n_meshes']} meshes)" if surface else label
        lines.append(f"| {label} | {m['bit_acc']:.4f} | {m['bit_acc_std']:.4f} | {m['psnr_object']:.2f} | "
                     f"{m['ssim_object']:.4f} | {m['flip_object']:.4f} | {m['psnr_texture_shown']:.2f} | {m['psnr_texture']:.2f} | "
                     f"{m['psnr_render']:.2f} |")
    if shipped is not None:
        lines += ["", f"The table marks and reads every mesh on the model's own grid. As `meshseal embed` marks each mesh "
                  f"(its cell grid sized to the texture's footprint; within its FLIP budget {shipped['max_flip']:g}: "
                  f"{shipped['strength_lowered']:.1%} of the meshes marked at a lower strength, mean strength "
                  f"{shipped['strength_mean']:.3f}) and `meshseal detect` reads a picture whose camera its "
                  f"metadata gives, the same {shipped['n_meshes']} meshes x {shipped['n_views']} seed views: bit accuracy "
                  f"**{shipped['bit_acc_known_camera']:.4f}**, detected at FPR {shipped['fpr_threshold']:g} "
                  f"{shipped['tpr_known_camera']:.3f}, exact message {shipped['exact_message_known_camera']:.3f}, "
                  f"object PSNR {shipped['psnr_object']:.2f} dB, object FLIP {shipped['flip_object']:.4f}, "
                  f"{shipped['seconds_per_picture']:.2f} s per picture."]
        uv_mapped, palette = shipped["by_uv_map"]["uv_mapped"], shipped["by_uv_map"]["palette"]
        lines += ["", f"Split by how the mesh uses its texture: {uv_mapped['pictures']} pictures of meshes with a UV map "
                  f"read **{uv_mapped['bit_acc_known_camera']:.4f}** (detected {uv_mapped['tpr_known_camera']:.3f}); "
                  f"{palette['pictures']} of meshes that use the texture as a colour palette (half their surface or more "
                  f"on faces without UV area) read **{palette['bit_acc_known_camera']:.4f}** (detected "
                  f"{palette['tpr_known_camera']:.3f}; object PSNR {palette['psnr_object']:.2f} dB, FLIP "
                  f"{palette['flip_object']:.4f}): such a face shows one texel wherever it is seen, so `meshseal embed` "
                  "first gives those faces charts of their own (`methods.charts`), filled with the colour they showed, "
                  "and the mark lies there as on any UV-mapped surface."]
    if attacked is not None:
        from meshseal.commands.model import attack_table

        lines += ["", f"## The road to the web ({attacked['n_meshes']} test meshes x 1 seed view, {args.size}^2, camera known)",
                  "", f"Each mesh marked as `meshseal embed` marks it (object PSNR {attacked['psnr_object']:.2f} dB, object "
                  f"FLIP {attacked['flip_object']:.4f}, 95th percentile {attacked['flip_object_p95']:.4f}; texture PSNR over the "
                  f"shown texels {attacked['psnr_texture_shown']:.2f} dB), rendered, saved as 8-bit PNG, put through each attack (Pillow's "
                  "encoders with their defaults: JPEG 4:2:0) and read with the camera known, as `meshseal eval --data "
                  f"{args.data} --meshes {args.attack_meshes} --size {args.size} --attacks {args.attacks} --model {args.name}` "
                  "prints it; detected at FPR 1e-6.", "", attack_table(attacked["attacks"])]
    if registered is not None:
        pose = registered["pose_error_px"]
        lines += ["", f"End to end as `meshseal detect` runs it on a picture without metadata, on the first "
                  f"{registered['n_meshes']} test meshes (one {args.size}^2 picture each, seed view, 8-bit values, object "
                  "found from the plain random background, camera registered against the original mesh): bit accuracy "
                  f"**{registered['bit_acc']:.4f}** (std {registered['bit_acc_std']:.4f}; "
                  f"{registered['bit_acc_known_camera']:.4f} with the true camera), registration success (pose error < "
                  f"0.5 px or IoU >= 0.95) {registered['registration_success']:.3f}, pose error median {pose['median']} px, "
                  f"90th percentile {pose['p90']} px, {registered['seconds_per_picture']:.1f} s per picture."
                  + (" This row too marks each mesh as `meshseal embed` does." if shipped is not None else "")]
    if surface:
        how = ("the bits from its columns" if method.name == "surface" else
               f"framed to {config['frame_size']}^2 and read by the learned decoder")
        lines += ["", "Each picture is read as `meshseal detect --model NAME PICTURE` reads it (no `--mesh`, no metadata): "
                  f"the object found from the plain background, {how}. A blind model reports raw "
                  "bits; `--expect TEXT` / `--expect-id N` (models with a payload schema) test one known message: the "
                  "binomial p-value of the bits that agree with it, detected only if the error-correcting code also "
                  "reads that message."]
        if method.name == "surface":
            lines[-1] += (" The mark is visible where the texture is flat (chroma bands that follow the object's x: "
                          "docs/preview_blind_bunny.png): it buys blind reading at the paper's PSNR, and the informed "
                          "`default` stays the invisible choice when the original mesh is at hand.")
    lines += ["", "Object PSNR, SSIM and FLIP compare the marked and original mesh rendered from the same view and light "
              "over the object's pixels (8-bit values); frame PSNR is over the whole frame, as the seed paper reports "
              "(the background inflates it). Seed paper (Table 4/5): 0.897 bit accuracy at 8 bits and 0.636 at 32 bits "
              "(texture only), rendered PSNR about 35 dB.", ""]
    card = WEIGHTS / f"{args.name}.md"
    card.write_text("\n".join(lines))
    print(f"wrote {target} and {card}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
