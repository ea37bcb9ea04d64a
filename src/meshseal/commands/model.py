"""`meshseal embed | detect | eval | train | models`: the watermarking model from the command line."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from contextlib import closing
from pathlib import Path

from ..errors import MeshsealError
from ..mesh_formats import file_type
from ..threads import available_cores
from ._common import (Stages, positive_int, require_files, require_mesh, require_messages, require_model,
                      require_picture, sampler)


def register(subparsers) -> None:
    embed = subparsers.add_parser("embed", help="hide a message in a mesh file",
                                  description="Watermark a mesh: writes the same format, never over the input.")
    embed.add_argument("input", type=Path, help="mesh file (.obj, .glb, .gltf, .ply, .off, .stl)")
    embed.add_argument("-o", "--output", type=Path, required=True,
                       help="output mesh file (same format; an OBJ's textures keep their names with the output's "
                            "suffix, e.g. wood_marked.jpg, and their format: JPEG at quality 95, 4:4:4)")
    what = embed.add_mutually_exclusive_group(required=True)
    what.add_argument("--message", help="text to hide (UTF-8; the default model holds 4 bytes, error-corrected)")
    what.add_argument("--id", type=_asset_id, help="an integer asset ID to hide (the default model: 0 to 2^32 - 1)")
    what.add_argument("--bits", help="raw bits to hide, no error correction (research): 0/1 of the model's length")
    _key_argument(embed)
    embed.add_argument("--model", default=None, help="shipped model name or .safetensors path (default: default)")
    embed.add_argument("--strength", type=_strength_up_to(10.0, loudest=True), default=None,
                       help="spread-spectrum models: the mark's amplitude, 1 being the default one; 2 is 6 dB "
                            "louder (more robust, more visible), 0.5 6 dB quieter. Not given: 1, lowered where "
                            "needed to keep the mark's FLIP within --max-flip. Given: used as is (add --max-flip to "
                            "keep the budget too). 'max': the loudest the renders allow (FLIP within --max-flip, "
                            "object PSNR at least 42 dB, at most 4): more robust to JPEG, WebP and resizing, the "
                            "texture's own PSNR under 40 dB")
    embed.add_argument("--max-flip", type=_budget, default=None,
                       help="spread-spectrum models: lower the strength until the mark's mean FLIP over the object "
                            "in the report's renders is at most this (default 0.03; none by default when --strength "
                            "is given or --views is 0; 0: no budget)")
    embed.add_argument("--views", type=positive_int(64, minimum=0), default=4,
                       help="views for the visibility figures (default 4; 0: none, faster)")
    embed.add_argument("--preview", type=Path, default=None,
                       help="write a PNG sheet: columns original | marked | difference x4, a row per material "
                            "texture and one render")
    embed.add_argument("--up", choices=("y", "z"), default=None, help="the file's up axis (default: by format)")
    embed.add_argument("--json", action="store_true", help="print one JSON object")
    embed.set_defaults(func=run_embed)

    detect = subparsers.add_parser(
        "detect", help="read the message from pictures of a marked mesh",
        description="Read the mark from each picture (any size; a plain or busy background; the camera from "
                    "the PNG metadata `meshseal render` writes, else found by registration) and print whether it "
                    "is there under the key, its p-value and the message. Where a plausible mistake explains "
                    "'not detected' (the marked mesh given as --mesh, a picture of another mesh) the line says so.",
        epilog="exit status: 0 a mark detected (several pictures: in at least one; --pool: in the pool; models "
               "that only print raw bits: 0), 1 no mark detected in any picture, 2 an error (bad arguments, or "
               "a picture that could not be read: the others are still read and printed).")
    detect.add_argument("images", type=Path, nargs="+", help="image files (PNG, JPEG, ...) or folders of them")
    detect.add_argument("--model", default=None,
                        help="shipped model name or .safetensors path (default: default; `meshseal models` lists them)")
    detect.add_argument("--mesh", type=Path, default=None,
                        help="the original (unmarked) mesh file: informed models, like the default, need it")
    detect.add_argument("--register", action="store_true",
                        help="find the picture's camera by registration even if the picture carries one")
    detect.add_argument("--quick", action="store_true",
                        help="for a scan of many pictures, most of them of other meshes: register without "
                             "trying other cuts of the object and more views where the first does not fit "
                             "(such pictures read several times faster; a few pictures of the mesh are missed)")
    detect.add_argument("--fov", type=float, default=60.0,
                        help="the picture's vertical field of view in degrees, where registration starts "
                             "(default 60; it refines it where the texture says otherwise)")
    _key_argument(detect)
    expect = detect.add_mutually_exclusive_group()
    expect.add_argument("--expect", default=None, help="test for this one text message (p-value of the match)")
    expect.add_argument("--expect-id", type=_asset_id, default=None, help="test for this one asset ID")
    expect.add_argument("--expect-ids", type=Path, default=None, metavar="FILE",
                        help="test for the asset IDs listed in FILE, one a line ('#' starts a comment): which "
                             "of them the picture carries, its p-value paying for the list's length")
    detect.add_argument("--pool", action="store_true",
                        help="decide once for all the pictures (views of one asset), adding their evidence")
    detect.add_argument("--json", "--jsonl", dest="json", action="store_true",
                        help="one JSON object per picture (or per pool), one per line")
    detect.add_argument("--workers", type=positive_int(64), default=None,
                        help="processes reading pictures at once (default: this one, until the pictures "
                             f"left would be read sooner by one process per core, at most {MAX_WORKERS}, "
                             "counting the seconds each takes to start)")
    detect.set_defaults(func=run_detect)

    evaluate = subparsers.add_parser("eval", help="measure a model on a dataset split")
    evaluate.add_argument("--data", type=Path, required=True,
                          help="dataset folder (meshseal data build), or a folder of your own mesh files: each "
                               "textured single-material mesh in it, with --attacks or --register")
    evaluate.add_argument("--split", default="test", choices=("train", "test", "test_cc0", "all"))
    evaluate.add_argument("--model", default=None, help="shipped model name or .safetensors path (default: default)")
    evaluate.add_argument("--views", type=positive_int(100), default=1, help="views per mesh (default 1)")
    evaluate.add_argument("--meshes", type=int, default=None, help="at most this many meshes (default all)")
    evaluate.add_argument("--start", type=positive_int(10 ** 9, 0), default=0,
                          help="skip the split's first START meshes (with --register or --attacks): a slice, "
                               "--start S --meshes N, so that slices run in processes of their own; each slice "
                               "draws its own views and messages (default 0)")
    evaluate.add_argument("--protocol", choices=("seed",), default=None,
                          help="seed: the paper's protocol (its camera and light ranges, meshes with spherical UVs "
                               "and noise or real textures, 600 x 400 pictures: --sampler paper --texture-kinds "
                               "noise,real)")
    evaluate.add_argument("--sampler", type=sampler, default=None, metavar="{paper,any}",
                          help="camera and light ranges: 'paper' (default) the seed paper's (Yoo et al. 2022), "
                               "'any' all around ('seed' is accepted for 'paper')")
    evaluate.add_argument("--size", type=positive_int(2048), default=None,
                          help="square render size (default 128; --protocol seed and the blind surface models: "
                               "the paper's 600 x 400)")
    evaluate.add_argument("--distortion-3d", type=float, default=0.0, help="3D distortion strength (0..1)")
    evaluate.add_argument("--distortion-2d", type=float, default=0.0, help="2D attack strength (0..1)")
    evaluate.add_argument("--texture-kinds", default=None,
                          help="only items with these texture kinds, comma-separated (own,real,noise)")
    evaluate.add_argument("--seed", type=int, default=0)
    evaluate.add_argument("--register", action="store_true",
                          help="informed models: detect as `meshseal detect --register` does (--views pictures per "
                               "mesh without metadata, camera found by registration, also pooled; slow)")
    evaluate.add_argument("--max-flip", type=_budget, default=None,
                          help="with --register, spread-spectrum models: mark each mesh under this FLIP budget, as "
                               "`meshseal embed` does (default 0.03; 0: strength 1 throughout)")
    evaluate.add_argument("--strength", type=_strength, default=None,
                          help="spread-spectrum models: mark each mesh at this strength, as `meshseal embed "
                               "--strength` does: used as given, unless --max-flip is given too; 'max': the "
                               "loudest within --max-flip and object PSNR 42 dB, as `embed --strength max` marks")
    evaluate.add_argument("--light-gain", type=_light_gain, default=1.0, metavar="G",
                          help="informed models: light the pictures G times as strongly as the sampler's lights, so "
                               "that highlights clip (the `clipped` kind of the by-kind table); the mark's FLIP budget "
                               "is measured as `meshseal embed` measures it, under its own lights (default 1)")
    evaluate.add_argument("--attacks", default=None, metavar="LIST",
                          help="informed models: also read every picture after each of these attacks, comma-"
                               "separated, or 'all' (none, jpeg95, jpeg90, jpeg75, jpeg50, jpeg95_444, jpeg90_444 "
                               "(no chroma subsampling), webp80, resize0.5, "
                               "resize0.75, resize1.5, crop0.8, screenshot, jpeg90_screenshot, jpeg75_screenshot (a JPEG pasted into a "
                               "screenshot), jpeg75_crop0.8 (a JPEG cropped), brightness, noise2; on the marked asset before "
                               "it is rendered: texture_jpeg90, texture_half, texture_bc1, texture_bc7, obj_glb, "
                               "decimate0.5); the resizes, the crop and the screenshots need --register. Prints one "
                               "row an attack")
    evaluate.add_argument("--json", action="store_true", help="print one JSON object")
    evaluate.set_defaults(func=run_eval)

    train = subparsers.add_parser("train", help="train a model from a config")
    train.add_argument("--config", type=Path, required=True, help="YAML config (see configs/)")
    train.add_argument("--out", type=Path, default=None, help="run folder (default runs/<config name>)")
    train.add_argument("--resume", action="store_true", help="continue from the run folder's checkpoint")
    train.add_argument("--data", type=Path, default=None, help="override the config's dataset folder")
    train.add_argument("--device", default="auto",
                       help="torch device: auto (cuda when one is there, else cpu) | cpu | cuda | cuda:N")
    train.add_argument("--time-limit", type=float, default=None, metavar="MINUTES",
                       help="override the config's time_limit_minutes (total training time, resumed runs included)")
    train.add_argument("--stop-at", type=int, default=None, metavar="STEP",
                       help="stop after this step; the learning-rate and mark schedules still run to the config's steps "
                            "(a run made in parts, each continued with --resume)")
    train.set_defaults(func=run_train)

    tune = subparsers.add_parser("finetune", help="fine-tune a learned decoder on another engine's pictures",
                                 description="Watermark training meshes, render them with ENGINE (cached, "
                                             "resumable), fine-tune the decoder on them and keep the result "
                                             "only if it loses no accuracy on the other engines.")
    tune.add_argument("--engine", choices=("ours", "gl", "cycles", "eevee", "workbench"), required=True)
    tune.add_argument("--data", type=Path, required=True, help="dataset folder (meshseal data build)")
    tune.add_argument("--model", default=None, help="shipped model name or .safetensors path (default: default)")
    tune.add_argument("--out", type=Path, default=None, help="output folder (default runs/finetune_<engine>)")
    tune.add_argument("--meshes", type=int, default=200, help="training meshes rendered (default 200)")
    tune.add_argument("--views", type=int, default=2, help="views per mesh (default 2)")
    tune.add_argument("--size", type=int, default=128, help="picture size (default 128)")
    tune.add_argument("--steps", type=int, default=500, help="fine-tuning steps (default 500)")
    tune.add_argument("--val-meshes", type=int, default=30, help="test meshes per engine for the keep decision")
    tune.add_argument("--engines", default="ours,gl,cycles,eevee,workbench",
                      help="engines the result must not lose accuracy on (comma-separated)")
    tune.add_argument("--seed", type=int, default=0)
    tune.set_defaults(func=run_finetune)

    models = subparsers.add_parser("models", help="list the shipped models")
    models.add_argument("--json", action="store_true", help="print a JSON list")
    models.set_defaults(func=run_models)


def _key_argument(parser) -> None:
    parser.add_argument("--key", default=None,
                        help="secret key (default: $MESHSEAL_KEY, else the public key anyone can read)")


def _key(args) -> str | None:
    """--key, else $MESHSEAL_KEY (keeps the key out of shell history), else None (the public key)."""
    import os

    key = args.key if args.key is not None else os.environ.get("MESHSEAL_KEY")
    if key is not None and not key:
        raise MeshsealError("the key is empty; give a non-empty --key or MESHSEAL_KEY, or none for the public key")
    return key


def _asset_id(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got '{text}'") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"an asset ID is not negative, got {value}")
    return value


LOUDEST = "max"  # `--strength max`: the loudest strength within the budgets (`evaluation.metrics.LOUDEST`, not imported: no torch here)


def _strength_up_to(limit: float, loudest: bool = False):
    """An argparse type: a strength in (0, limit] (`embed`: the API's own range, checked before it loads),
    or with `loudest` the word LOUDEST."""
    def parse(text: str) -> float | str:
        if loudest and text.strip().lower() == LOUDEST:
            return LOUDEST
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number{' or max' if loudest else ''}, got '{text}'") from None
        if not 0.0 < value <= limit:
            raise argparse.ArgumentTypeError(f"expected a strength in (0, {limit:g}], got {value}")
        return value
    return parse


_strength = _strength_up_to(100.0, loudest=True)


def _light_gain(text: str) -> float:
    """eval --light-gain: a factor in (0, 10] on the pictures' lights (argparse type)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got '{text}'") from None
    if not 0.0 < value <= 10.0:
        raise argparse.ArgumentTypeError(f"a light gain is in (0, 10], got {text}")
    return value


def _budget(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got '{text}'") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"a FLIP budget is between 0 and 1, got {text}")
    return value


def run_embed(args) -> int:
    if args.message is not None and not args.message.strip():
        raise MeshsealError("--message is empty (or only spaces): give the text to hide (the default model holds 4 bytes), "
                            "or an asset ID with --id")
    require_mesh(args.input)
    require_model(args.model)
    # what the arguments alone decide, before the model and the mesh are loaded (answered at once)
    file_type(args.output)
    if args.preview is not None:
        if args.views == 0:
            raise MeshsealError("--preview shows a render: give --views 1 or more")
        if os.path.realpath(args.preview) == os.path.realpath(args.output):
            raise MeshsealError(f"{args.preview}: the preview would overwrite the output; choose another path")
    if args.max_flip is not None and args.max_flip > 0 and args.views == 0:
        raise MeshsealError("--max-flip measures the mark in renders: give --views 1 or more, or --max-flip 0")
    loudest = args.strength == LOUDEST
    if loudest and (args.views == 0 or args.max_flip == 0):
        raise MeshsealError("--strength max fills the visibility budget measured in renders: give --views 1 or more "
                            "and a --max-flip above 0")
    if args.bits is None:
        require_messages([args.message if args.id is None else args.id], args.model)
    stage = Stages()
    stage(f"loading the model and {args.input.name}")
    from ..api import load
    from ..evaluation.metrics import MAX_FLIP, MIN_OBJECT_PSNR
    from ..mesh import load as load_mesh, save
    from ..mesh.io import check_output

    watermarker = load(args.model)
    mesh = load_mesh(args.input, up_axis=args.up, cache="fill")  # for the detections after it
    check_output(args.output, mesh.source.input_files)
    if args.preview is not None:
        check_output(args.preview, mesh.source.input_files)
    key = _key(args)
    base = watermarker.layout(mesh, note=True)  # what the mark is added to (palette faces charted), charted once
    message = {"bits": args.bits} if args.bits is not None else {"message": args.message if args.id is None else args.id}
    asked = 1.0 if args.strength is None or loudest else args.strength
    default_budget = (args.strength is None or loudest) and args.views > 0
    max_flip = args.max_flip if args.max_flip is not None else (MAX_FLIP if default_budget else 0.0)
    budget = max_flip > 0 and watermarker.method.flip_budget
    if loudest and not watermarker.method.flip_budget:
        raise MeshsealError(f"--strength max is for spread-spectrum models (their strength scales the mark), not "
                            f"the {watermarker.method.name} method")
    stage(f"marking the texture{'s' if sum(m.texture is not None for m in base.materials) > 1 else ''}"
          + (f" as loud as FLIP {max_flip} and object PSNR {MIN_OBJECT_PSNR:g} dB allow ({args.views} renders)" if loudest
             else f" and keeping the mark's FLIP within {max_flip} ({args.views} renders)" if budget else ""))
    if loudest:
        marked, strength = watermarker.embed_loudest(base, **message, key=key, max_flip=max_flip, views=args.views)
    elif budget:
        marked, strength = watermarker.embed_within(base, **message, key=key, strength=asked, max_flip=max_flip,
                                                    views=args.views)
    else:
        marked, strength = watermarker.embed(base, **message, key=key, strength=asked), asked
    stage(f"writing {args.output}")
    written = save(marked, args.output)
    stage("measuring what the mark changed" + (f" ({args.views} renders)" if args.views else ""))
    from ..evaluation.reports import embed_report, write_preview

    report, renders = embed_report(base, marked, args.views)
    report |= {"model": watermarker.name, "n_bits": watermarker.n_bits, "strength": round(strength, 4),
               "strength_asked": LOUDEST if loudest else asked, "max_flip": max_flip if budget else None,
               "cells": watermarker.mark_grid(base), "keyed": key is not None, "output": str(args.output)}
    if args.preview is not None:
        stage(f"writing the preview {args.preview}")
        write_preview(args.preview, base, marked, renders)
        report["preview"] = str(args.preview)
    if args.json:
        print(json.dumps(report))
    else:
        print(f"wrote {', '.join(str(p) for p in written)}")
        psnr_texture = report["psnr_texture"]
        cells = f" ({report['cells']}^2 cells)" if report["cells"] else ""
        shown = report["psnr_texture_shown"]
        shown = f" (over the texels the mesh shows: {shown} dB)" if shown is not None else ""
        print(f"texture PSNR {psnr_texture if psnr_texture is not None else 'n/a'} dB{shown}{cells}, normal change "
              f"{report['normal_angle_deg']:.3f} deg, uv shift {report['uv_shift_texels']:.3f} texels")
        if loudest:
            print(f"strength {strength:.3g}: the loudest within FLIP {max_flip} and object PSNR {MIN_OBJECT_PSNR:g} dB "
                  "(--strength max)")
        elif strength != asked:
            reached = report.get("flip_object") is None or report["flip_object"] <= max_flip
            goal = f"to keep the mark's FLIP at most {max_flip}" if reached else \
                f"(the floor; the mark's FLIP stays above {max_flip})"
            print(f"strength {asked:g} lowered to {strength:.3g} {goal} (--max-flip)")
        if args.views:
            figure = lambda key, digits: "n/a" if report[key] is None else f"{report[key]:.{digits}f}"  # noqa: E731
            print(f"renders over the object's pixels ({args.views} views, 256^2): PSNR {figure('psnr_object', 2)} dB, "
                  f"SSIM {figure('ssim_object', 4)}, FLIP {figure('flip_object', 4)} "
                  f"(whole frame: PSNR {report['psnr_frame']:.2f} dB, SSIM {report['ssim_frame']:.4f})")
        if args.preview is not None:
            print(f"wrote preview {args.preview}")
    return 0


IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".webp", ".bmp", ".tif", ".tiff", ".gif"}
MAX_WORKERS = 8  # the default pool's processes at most (one per core)


def picture_paths(paths: list[Path]) -> list[Path]:
    """The pictures named: files as given, folders as their picture files (by suffix, sorted)."""
    pictures = []
    for path in paths:
        if path.is_dir():
            found = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
            if not found:
                raise MeshsealError(f"{path}: no pictures in this folder ({', '.join(sorted(IMAGE_SUFFIXES))})")
            pictures.extend(found)
        else:
            pictures.append(path)
    return pictures


def _expected(args):
    """What `detect` tests for: --expect's text, --expect-id's ID, --expect-ids' list (a tuple), or None."""
    if getattr(args, "expect_ids", None) is not None:
        return read_ids(args.expect_ids)
    return args.expect if args.expect_id is None else args.expect_id


def read_ids(path: Path) -> tuple[int, ...]:
    """Asset IDs from a text file, one a line; blank lines and '#' comments skipped, repeats kept once."""
    require_files((path, "list of asset IDs"))
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as error:
        raise MeshsealError(f"cannot read the list of asset IDs {path}: {error}") from None
    ids = {}
    for number, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        try:
            ids[_asset_id(text)] = None
        except argparse.ArgumentTypeError as error:
            raise MeshsealError(f"{path}, line {number}: {error}") from None
    if not ids:
        raise MeshsealError(f"{path} lists no asset IDs")
    return tuple(ids)


def _describe(result, expect=None) -> str:
    """One line for a person: the decision, the message, the evidence."""
    how = "" if result.camera is None else f", camera: {result.camera}"
    if result.registration_iou is not None and "silhouette IoU" not in (result.reason or ""):  # said once
        how += f" (silhouette IoU {result.registration_iou:.3f})"
    if result.detected is None:
        return f"bits {result.bits}{how}"
    p_value = f"p = {result.p_value:.2g}"
    if result.detected and result.named is False:  # the pilot found a mark the match does not name
        what = f"any of the {len(expect)} IDs listed" if isinstance(expect, tuple) else json.dumps(expect)
        reads = ("the message is too faint to read" if result.message is None
                 else f"the code reads {json.dumps(result.message)}")
        return f"detected: a mark under this key ({p_value}, whatever its message{how}), but the match does not name {what}: {reads}"
    if isinstance(expect, tuple):  # the owner's list
        listed = f"{len(expect)} ID{'s' if len(expect) != 1 else ''} listed"
        if result.detected:
            corrected = f", {result.errors_corrected} bit(s) off" if result.errors_corrected else ""
            faint = ("; too faint for the code to read alone, so an ID outside the list is not ruled out"
                     if result.list_only else "")
            return f"detected {json.dumps(result.message)}, of the {listed} ({p_value} of the match{corrected}{how}){faint}"
        if result.message is not None:
            return f"none of the {listed}: the mark reads {json.dumps(result.message)} ({p_value} of the best match{how})"
        return f"none of the {listed} ({p_value} of the best match{how})" + (f": {result.reason}" if result.reason else "")
    if not result.detected and expect is not None and result.message is not None:
        return f"not {json.dumps(expect)}: the mark reads {json.dumps(result.message)} ({p_value} of the match{how})"
    if not result.detected:
        return f"not detected ({p_value}{how})" + (f": {result.reason}" if result.reason else "")
    if result.message is None and expect is not None:  # the match found the mark; the code alone cannot read it
        return (f"detected: a mark under this key agreeing with {json.dumps(expect)} ({p_value} of the match{how}); "
                "too faint to decode, so another message under this key is not ruled out")
    if result.message is None:
        return f"detected, message unreadable ({p_value}{how})"
    corrected = f", {result.errors_corrected} bit(s) corrected" if result.errors_corrected else ""
    return f"detected {json.dumps(result.message)} ({p_value}{corrected}{how})"


def run_detect(args) -> int:
    started = time.perf_counter()  # what this process took to get ready is what a worker would take
    # one picture named: a mistyped name is answered at once; of several, a missing one is that line's error
    require_mesh(args.mesh)
    require_files(*([(args.images[0], "picture or folder")] if len(args.images) == 1 else []))
    require_model(args.model)
    if not 1.0 <= args.fov <= 170.0:
        raise MeshsealError(f"--fov must be between 1 and 170 degrees, got {args.fov}")
    expect = _expected(args)
    if expect is not None:
        require_messages(expect if isinstance(expect, tuple) else [expect], args.model)
    pictures = picture_paths(args.images)
    if len(args.images) == 1 and len(pictures) == 1:  # one picture named: one that is none is answered at once
        require_picture(pictures[0])
    stage = Stages()
    stage("loading the model" + (f" and {args.mesh.name}" if args.mesh is not None else ""))
    from ..api import load

    watermarker = load(args.model)
    key = _key(args)
    original = None
    if watermarker.informed:
        if args.mesh is None:
            raise MeshsealError(f"model '{watermarker.name}' reads pictures with the original mesh: add --mesh FILE")
        original = watermarker.original(args.mesh)
    if expect is not None:  # a message that cannot be a message of this model: say so before any work
        from .. import payload

        if isinstance(expect, tuple):
            payload.encode_many(expect, key, watermarker.n_bits)
        else:
            payload.encode(expect, key, watermarker.n_bits)
    failed, readings, decisions = 0, [], []
    progress = None
    if len(pictures) == 1:
        stage(f"reading {pictures[0]}")
    if sys.stderr.isatty() and len(pictures) > 1:
        from tqdm import tqdm

        progress = tqdm(total=len(pictures), unit="picture", file=sys.stderr)
    workers = None if args.workers is None else min(args.workers, len(pictures))  # None: as it pays
    start_cost = time.perf_counter() - started
    with closing(_readings(args, watermarker, original, pictures, workers, expect, start_cost)) as read:
        for path, outcome, error in read:  # closing: the worker pool ends even if a line fails
            failed += _report(args, watermarker, original, path, outcome, error, progress, key, expect, readings,
                              decisions)
    if progress is not None:
        progress.close()
    if args.pool and readings:
        result = watermarker.decision(readings, original, key, expect)
        decisions.append(result)
        print(json.dumps(result.to_dict()) if args.json else f"{len(readings)} pictures pooled: {_describe(result, expect)}")
    if (not failed and key is None and decisions and watermarker.method.calibrated
            and not any(r.detected or r.reason or r.message is not None for r in decisions)):
        print("meshseal: note: read under the public key (no --key, no $MESHSEAL_KEY): a mark made under a "
              "secret key reads as no mark", file=sys.stderr)
    # With --expect the question is the message: a mark the match does not name (a pilot's) exits 1.
    return detect_status(failed, [r.detected if r.detected is None else r.detected and r.named is not False for r in decisions])


def detect_status(failed: int, decisions: list) -> int:
    """`meshseal detect`'s exit status: 2 if any picture could not be read, else 1 if the model decided
    and no picture (or pool) was detected, else 0 (one detected, or no decision: raw bits)."""
    if failed:
        return 2
    decided = [d for d in decisions if d is not None]
    return 1 if decided and not any(decided) else 0


def _report(args, watermarker, original, path, outcome, error, progress, key, expect, readings, decisions) -> int:
    """Print one picture's line (or keep its reading for the pool; its Detection goes to `decisions`);
    1 if it could not be read. `outcome`: the picture's Detection, or with --pool its reading."""
    if error is not None:
        (progress.write if progress else lambda line: print(line, file=sys.stderr))(f"meshseal: error: {error}")
        if args.json:
            print(json.dumps({"image": str(path), "error": str(error)}), flush=True)
    if progress is not None:
        progress.update()
    if error is not None:
        return 1
    if args.pool:
        readings.append(outcome)
        return 0
    decisions.append(outcome)
    line = json.dumps({"image": str(path)} | outcome.to_dict()) if args.json else f"{path}: {_describe(outcome, expect)}"
    if progress is not None and not args.json:
        progress.write(line)
    else:
        print(line, flush=True)
    return 0


def _readings(args, watermarker, original, paths: list[Path], workers: int | None, expect=None,
              start_cost: float = 0.0):
    """(path, Detection (with --pool: its reading), error text) of each picture, in order, tested for
    `expect` (`_expected`). With more than one worker, spawned processes (one thread each) load the
    model and the original once and detect in parallel; a pool's decision stays with the caller.
    `workers` None: this process reads the pictures one after another until `pool_pays` says the
    rest would be read sooner by one process per core (at most MAX_WORKERS), each of them taking
    `start_cost` seconds to start (this process's own, model and original included)."""
    task = (args.register, args.fov, _key(args), expect, args.pool, args.quick)
    if workers is None or workers <= 1:
        from ..render import compiled

        compiled.for_pictures(len(paths))  # several pictures: the renderer's compiled kernels pay at once
    if workers is None:
        seconds = []
        for done, path in enumerate(paths):
            cores = min(available_cores(), MAX_WORKERS, len(paths) - done)
            if pool_pays(seconds, len(paths) - done, cores, start_cost):
                yield from _pooled(args, original, paths[done:], cores, task)
                return
            begin = time.perf_counter()
            yield _read_one(watermarker, original, path, *task)
            seconds.append(time.perf_counter() - begin)
        return
    if workers <= 1:
        yield from (_read_one(watermarker, original, path, *task) for path in paths)
        return
    yield from _pooled(args, original, paths, workers, task)


def pool_pays(seconds: list[float], remaining: int, cores: int, start_cost: float) -> bool:
    """Whether `remaining` pictures would be read sooner by `cores` new worker processes than here, one
    after another, at the pace of the pictures read here so far (`seconds` each; the last one sets the
    pace: the first also paid one-time costs, which every worker pays again on top of `start_cost`).
    Judged from the second picture on: a registered picture takes seconds, one whose camera its file
    gives a few hundredths, so a folder of them starts a pool only when it is large."""
    if len(seconds) < 2 or cores < 2:
        return False
    pace = seconds[-1]
    warm_up = max(0.0, seconds[0] - pace)
    return pace * remaining * (1.0 - 1.0 / cores) > start_cost + warm_up


def _pooled(args, original, paths: list[Path], workers: int, task: tuple):
    """`_readings` of `paths` by `workers` spawned processes."""
    import multiprocessing

    from ..threads import worker_environment

    # Spawned, not forked: a fork after torch or numba started their threads can deadlock. One thread
    # per worker, set before the children import anything: thread pools of several processes spinning
    # against each other on the same cores cost many times the work (meshseal.threads).
    saved = dict(os.environ)
    os.environ.update(worker_environment())
    try:
        pool = multiprocessing.get_context("spawn").Pool(
            workers, _worker_start, (args.model, None if original is None else str(args.mesh)))
    finally:
        os.environ.clear()
        os.environ.update(saved)
    try:
        yield from pool.imap(_worker_read, [(path, *task) for path in paths])
    finally:
        pool.terminate()
        pool.join()


def _read_one(watermarker, original, path, register: bool, fov: float, key, expect, pool: bool, quick: bool = False):
    """A picture's Detection, as `Watermarker.detect` reads and decides it; with `pool`, its reading
    alone (the pool's evidence is added and decided once, `Watermarker.decision`)."""
    try:
        if pool:  # settled: no second look (a pool decides once), nothing but evidence to send back
            reading = watermarker.read(path, original, register=register, fov_y=fov, quick=quick)
            return path, watermarker.look_again(reading, original, search=False), None
        return path, watermarker.detect(path, original, key=key, expect=expect, register=register, fov_y=fov,
                                        quick=quick), None
    except MeshsealError as error:
        return path, None, str(error)


_WORKER: dict = {}


def _worker_start(model, mesh) -> None:
    from ..threads import configure

    configure(worker=True)
    from ..api import load
    from ..render import compiled

    compiled.load()  # a worker is started for many pictures: the compiled kernels pay at once

    watermarker = load(model)
    _WORKER.update(watermarker=watermarker, original=None if mesh is None else watermarker.original(mesh))


def _worker_read(task):
    return _read_one(_WORKER["watermarker"], _WORKER["original"], *task)


def run_eval(args) -> int:
    require_model(args.model)
    # neither a dataset nor a folder: answered before the heavy imports (a folder's contents are checked after)
    if not args.data.is_dir():
        raise MeshsealError(f"{args.data}: not a meshseal dataset (no manifest) nor a folder of meshes")
    attacks = None
    if args.attacks is not None:  # the names too (`evaluation.attacks` parses them without numpy or torch)
        from ..evaluation.attacks import GEOMETRIC, parse

        try:
            attacks = parse(args.attacks)
        except ValueError as error:
            raise MeshsealError(f"--attacks: {error}") from None
        moved = [name for name in attacks if name in GEOMETRIC]
        if moved and not args.register:
            raise MeshsealError(f"--attacks {','.join(moved)} change the picture's camera: add --register")
    if args.start and not (args.register or attacks):
        raise MeshsealError("--start slices the pictures read as `detect` reads them: add --register or --attacks")
    from ..api import load
    from ..data.dataset import MeshDataset
    from ..training.distortions import Distortions2D, Distortions3D
    from ..evaluation.evaluate import evaluate_registered
    from ..training.validate import evaluate
    from ..evaluation.metrics import MAX_FLIP

    watermarker = load(args.model)
    folder = not (args.data / "manifest.jsonl").is_file() and not (args.data / "manifest.csv").is_file()
    if folder and not (watermarker.informed and (args.register or args.attacks is not None)):
        raise MeshsealError(f"{args.data}: a folder of meshes (no manifest) is evaluated as `detect` reads pictures: "
                            f"give --attacks (e.g. none) or --register, with an informed model")
    kinds = args.texture_kinds.split(",") if args.texture_kinds else None
    if args.protocol == "seed":
        if args.sampler not in (None, "seed") or not set(kinds or ["noise"]) <= {"noise", "real"}:
            raise MeshsealError("--protocol seed uses the seed sampler and noise/real textures; drop --sampler any "
                                "and --texture-kinds own")
        kinds = kinds or ["noise", "real"]
    args.sampler = args.sampler or "seed"
    paper_size = (args.protocol == "seed" or watermarker.method.paper_pictures) and not args.register
    size = args.size or ((400, 600) if paper_size else 128)  # blind surface models read the paper's pictures
    if folder:  # the user's own assets, as they are
        from ..data.folder import AssetFolder

        dataset = AssetFolder(args.data)
        for path, why in dataset.skipped:
            print(f"meshseal: note: {path}: left out: {why}", file=sys.stderr)
    else:
        dataset = MeshDataset(args.data, args.split, seed=args.seed, texture_kinds=kinds)
    if len(dataset) == 0:
        kinds_note = f" of texture kinds {','.join(kinds)}" if kinds else ""
        raise MeshsealError(f"{args.data}: the {args.split} split has no items{kinds_note}")
    if args.start:
        if args.start >= len(dataset):
            raise MeshsealError(f"--start {args.start}: {args.data} has {len(dataset)} meshes in this split")
        from torch.utils.data import Subset

        dataset = Subset(dataset, range(args.start, len(dataset)))
    if attacks is not None and not watermarker.informed:
        raise MeshsealError(f"--attacks is for informed models; '{watermarker.name}' reads pictures blind")
    if args.register or attacks:
        if not watermarker.informed:
            raise MeshsealError(f"--register is for informed models; '{watermarker.name}' reads pictures blind")
        log = None if args.json else print
        default_budget = args.strength is None or args.strength == LOUDEST
        max_flip = (MAX_FLIP if default_budget else None) if args.max_flip is None else (args.max_flip or None)
        if args.strength == LOUDEST and max_flip is None:
            raise MeshsealError("--strength max fills the FLIP budget: give a --max-flip above 0")
        metrics = evaluate_registered(watermarker.model, dataset, args.meshes, args.seed, max(size, 64),
                                      args.sampler, log if args.register else None, views=args.views,
                                      register=args.register, max_flip=max_flip, attacks=attacks,
                                      strength=1.0 if args.strength is None else args.strength, by_item=folder,
                                      light_gain=args.light_gain)
    else:
        metrics = evaluate(watermarker.model, dataset, args.meshes, args.views, args.seed, size, args.sampler,
                           distortions_3d=Distortions3D(args.distortion_3d) if args.distortion_3d > 0 else None,
                           distortions_2d=Distortions2D(args.distortion_2d) if args.distortion_2d > 0 else None,
                           progress=sys.stderr.isatty())
    metrics = {"model": watermarker.name, "split": "folder" if folder else args.split, "start": args.start,
               "sampler": args.sampler,
               "protocol": args.protocol or "ours", "texture_kinds": kinds or "all",
               "size": list(size) if isinstance(size, tuple) else size} | metrics
    if args.json:
        print(json.dumps(metrics))
    else:
        table = metrics.pop("attacks", None)
        kinds = metrics.pop("by_kind", None)
        items = metrics.pop("by_item", None)
        for key, value in metrics.items():
            print(f"{key}: {value:.4f}" if isinstance(value, float) else f"{key}: {value}")
        if table:
            print(attack_table(table))
        if kinds:
            print(kind_table(kinds, list(table or [])))
        if items:
            print(kind_table(items, list(table or []), "mesh"))
    return 0


def kind_table(kinds: dict, attacks: list[str], what: str = "kind") -> str:
    """`evaluate_registered`'s detection rates by kind of picture (`evaluation.evaluate.picture_kinds`), or
    by item (`what` "mesh"): one row each, the pictures as read, then after each attack."""
    figure = lambda value: "-" if value is None else f"{value:.2f}"  # noqa: E731
    row_of = lambda cells: "| " + " | ".join(cells) + " |"  # noqa: E731
    lines = [row_of([what, "pictures", "object FLIP", "detected", *attacks]), row_of(["---"] * (4 + len(attacks)))]
    lines += [row_of([kind, str(row["pictures"]), f"{row['flip_object']:.4f}", figure(row["detected"]),
                      *(figure(row.get(name)) for name in attacks)]) for kind, row in kinds.items()]
    return "\n".join(lines)


def attack_table(table: dict) -> str:
    """`evaluate_registered`'s per-attack figures as a Markdown table; registered, a column more: the
    same pictures detected when read with their camera (where the attack keeps it), what registration
    cost."""
    figure = lambda value: "-" if value is None else f"{value:.3f}"  # noqa: E731
    known = any("detected_known_camera" in row for row in table.values())
    lines = ["| attack | pictures | detected | exact | wrong message | detected, message named | detected and named, "
             "1,000 IDs listed | bit accuracy | seconds |" + (" detected, camera known |" if known else ""),
             "|---|---|---|---|---|---|---|---|---|" + ("---|" if known else "")]
    lines += [f"| {name} | {row['pictures']} | {figure(row['detected'])} | {figure(row['exact'])} | {figure(row.get('wrong'))} | "
              f"{figure(row.get('named'))} | {figure(row.get('listed'))} | {figure(row['bit_acc'])} | {row['seconds']:.2f} |"
              + (f" {figure(row.get('detected_known_camera'))} |" if known else "")
              for name, row in table.items()]
    return "\n".join(lines)


def _train_device(name: str) -> str:
    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(name)
    except RuntimeError:
        raise MeshsealError(f"--device {name}: not a torch device (auto | cpu | cuda | cuda:N)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise MeshsealError(f"--device {name}: this machine has no CUDA device")
    return name


def run_train(args) -> int:
    require_files((args.config, "config file"))
    from ..training.train import TrainConfig, Trainer

    config = TrainConfig.load(args.config)
    if args.data is not None:
        config.data = str(args.data)
    if not Path(config.data).is_dir():
        raise MeshsealError(f"{config.data}: no dataset folder; build one with 'meshseal data build --out {config.data}'")
    if args.time_limit is not None:
        config.train.time_limit_minutes = args.time_limit
    if args.stop_at is not None:
        if args.stop_at < 1:
            raise MeshsealError(f"--stop-at {args.stop_at}: a step number of 1 or more")
        config.train.stop_at = args.stop_at
    out = args.out or Path("runs") / config.name
    trainer = Trainer(config, out, resume=args.resume, device=_train_device(args.device))
    summary = trainer.fit()
    from ..training.distributed import leave

    leave(trainer.world)
    if trainer.world.main:
        print(json.dumps(summary | {"out": str(out)}))
    return 0


def run_finetune(args) -> int:
    require_model(args.model)
    require_files((args.data, "dataset folder"))
    from ..api import load
    from ..data.dataset import MeshDataset
    from ..training.finetune import FinetuneConfig, finetune

    watermarker = load(args.model)
    if not (args.data / "manifest.jsonl").is_file() and not (args.data / "manifest.csv").is_file():
        raise MeshsealError(f"{args.data}: not a meshseal dataset (no manifest); build one with 'meshseal data build'")
    engines = [e for e in args.engines.split(",") if e]
    unknown = [e for e in engines if e not in ("ours", "gl", "cycles", "eevee", "workbench")]
    if unknown:
        raise MeshsealError(f"unknown engine(s) in --engines: {', '.join(unknown)}")
    cfg = FinetuneConfig(engine=args.engine, meshes=args.meshes, views=args.views, size=args.size, steps=args.steps,
                         val_meshes=args.val_meshes, engines=engines, seed=args.seed)
    out = args.out or Path("runs") / f"finetune_{args.engine}"
    report = finetune(watermarker.model, MeshDataset(args.data, "train", seed=args.seed),
                      MeshDataset(args.data, "test", seed=args.seed), cfg, out)
    print(json.dumps({k: report[k] for k in ("engine", "kept", "before", "after", "train_pictures")} | {"out": str(out)}))
    return 0


def run_models(args) -> int:
    from ..api import shipped_models

    models = shipped_models()
    if args.json:
        print(json.dumps(models))
    else:
        for m in models:
            kind = "informed (needs the original mesh)" if m["informed"] else "blind"
            payload = f"{m['payload_bits']} payload bits" if m["payload_bits"] is not None else "raw bits only"
            print(f"{m['name']}: method {m['method']}, {m['n_bits']} raw bits, {payload}, {m['strategy']}, {kind}"
                  f"{', calibrated p-values' if m['calibrated'] else ''}")
    return 0
