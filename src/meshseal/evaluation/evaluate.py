"""Evaluation as users detect: each test mesh marked as `meshseal embed` marks it, rendered, saved as
8-bit pictures, optionally attacked (`attacks`), and read as `meshseal detect` reads them (camera
known, or registered) through the `Watermarker` facade. The training pass's own measurement of a
split is `training.validate.evaluate`.

Deterministic for a seed: the same meshes, messages, cameras and lights every time.
"""

from __future__ import annotations

import math
import time
import zlib

import numpy as np
import torch

from ..data.dataset import collate
from ..models import WatermarkModel
from ..render import MeshRenderer
from ..methods.batches import batch_cell_width, batch_mark_grid, batch_texels_used, charted_item, unpadded
from .asset_attacks import ASSET_ATTACKS
from .asset_attacks import apply as attack_asset
from .attacks import GEOMETRIC, cropped_camera
from .attacks import apply as attack_picture
from .metrics import (
    BUDGET_VIEWS,
    LOUDEST,
    MAX_FLIP,
    seed_renders,
    shown_texture_psnr,
    strength_filled,
    strength_within,
    visibility,
)




# Kinds of picture the by-kind report splits out (`picture_kinds`), so that no class of failures hides in
# a mean: an object this small (pixels), highlights that clip (this share of the object's pixels at 255).
SMALL_OBJECT = 1500
CLIPPED = 0.2
# A texture whose cells are under this many pixels wide in a standard view (`models.spread.cell_pixels`) is
# minified even where the mark has no coarser grid for it: a picture point-samples such cells, and another
# engine's mipmaps, a resized picture or a camera a tenth of a pixel off lose them (experiments/minified_grid.py).
MINIFIED_BELOW = 0.75
KIND_ORDER = ("plain", "magnified", "minified", "clipped", "small")


def attack_stream(name: str) -> int:
    """The random stream of attack `name` (its canvas placement, its noise): from its name, so that an
    attack's pictures are the same whichever other attacks run beside it and in whatever order."""
    return zlib.crc32(name.encode("utf-8"))


def picture_kinds(encoder, grid: int | None, pictures: torch.Tensor, masks: torch.Tensor,
                  cell_width: float | None = None) -> list[list[str]]:
    """The kinds each of a mesh's pictures (V, 3, H, W in [0, 1], object masks (V, H, W)) belongs to:
    `magnified` / `minified` texture (a spread mark (`encoder`) laid on its fine / coarse `grid`
    because its cells would be over `fine_above` / under `coarse_below` pixels in a standard view; or,
    on the model's own grid, its cells `cell_width` px wide there, under MINIFIED_BELOW),
    `clipped` (at least CLIPPED of the object's pixels at white in some channel), `small` (fewer than
    SMALL_OBJECT object pixels); the others are `plain`. A picture can be of several kinds."""
    scale = None
    if grid is not None and grid != encoder.chips:
        scale = "magnified" if grid == encoder.fine_chips else "minified" if grid == encoder.coarse_chips else None
    elif cell_width is not None and cell_width < MINIFIED_BELOW:
        scale = "minified"
    kinds = []
    for picture, mask in zip(pictures, masks):
        pixels = int(mask.sum())
        white = (picture.amax(0) >= 254.5 / 255)[mask]
        named = [name for name, hit in ((scale, scale is not None),
                                        ("clipped", pixels > 0 and float(white.float().mean()) >= CLIPPED),
                                        ("small", pixels < SMALL_OBJECT)) if hit]
        kinds.append(named or ["plain"])
    return kinds


LISTED = 1000  # the owner's list of asset IDs in the `listed` figures: the mark's own and 999 others


def _listed(identity: int, seed: int, index: int, n_bits: int) -> tuple[int, ...]:
    """`LISTED` asset IDs, seeded per mesh, the mark's own among them at a random place."""
    from .. import payload

    rng = np.random.default_rng([seed, index, 7])
    others = [int(v) for v in rng.integers(0, 2 ** payload.payload_bits(n_bits), LISTED - 1) if int(v) != identity]
    others.insert(int(rng.integers(0, len(others) + 1)), identity)
    return tuple(others)


def _names(decision, identity: int) -> bool:
    """Whether a decision against a list detected the mark and named its own ID."""
    return bool(decision.detected) and decision.message == identity


def _named(decision) -> bool:
    """Whether a decision against the expected message detected the mark and the match named it (a
    model's pilot may detect a mark the match does not name)."""
    return bool(decision.detected) and decision.named is not False


def evaluate_registered(model: WatermarkModel, dataset, n_meshes: int | None = None, seed: int = 0,
                        size: int = 256, sampler: str = "seed", log=None, views: int = 1, register: bool = True,
                        max_flip: float | None = MAX_FLIP, attacks: list[str] | None = None,
                        strength: float = 1.0, by_item: bool = False, light_gain: float = 1.0) -> dict:
    """Informed models end to end, as `meshseal detect --register` runs: each test mesh is watermarked
    (with an error-corrected 32-bit ID when the model has a payload schema, else random raw bits),
    rendered `views` times (size x size 8-bit pictures, random views and lights from `sampler`'s
    ranges, plain random backgrounds), and each picture is read through `Watermarker.read` without
    metadata: object found, camera registered against the original mesh, picture un-rendered and
    decoded. Reports bit accuracy with the registered and the true camera, registration success and
    pose error, and for calibrated models the detection rate at the FPR threshold (TPR) and the exact-
    message rate, per picture and, with several views, pooled over each mesh's pictures. Slow.
    `register` False skips registration: the camera-known figures alone, as `meshseal detect` reads
    pictures with camera metadata (fast enough for the whole split). Calibrated models mark each mesh
    under `meshseal embed`'s FLIP budget `max_flip` (its 4 seed views; None: `strength` throughout),
    starting from `strength` as `embed --strength` does, and report the mean strength used and the share
    of meshes whose strength the budget lowered.
    `attacks` (names of `meshseal.attacks`): each 8-bit picture is also read after each attack (JPEG,
    WebP, resizing, crops, a screenshot, ...), registered (or, without `register`, with its camera:
    photometric attacks only), and `result["attacks"]` gives per attack the pictures, the share
    detected and read exactly, the bit accuracy and the seconds a picture; registered, also the share
    detected with the camera known (`<attack>_known_camera`: the true camera, or the crop's own,
    `attacks.cropped_camera`; none for a screenshot), what registration cost, and the median pose
    error in the attacked picture's pixels (`pose_error_px_median`; by item `<attack>_pose_px`). `named` (and
    `tpr_message_named`) is the share detected by the owner who names the message (`detect --expect`:
    the match's p-value, on the reading `detect` made without it); `listed` (and `tpr_among_listed`)
    the share detected and named by the owner who lists `LISTED` asset IDs, the mark's among them
    (`detect --expect-ids`: the best match's p-value times the list's length). `by_item`: also
    `result["by_item"]`, `by_kind`'s figures for each item (its `id`): a folder of the user's own meshes.
    `light_gain`: the pictures' lights that many times as strong as the sampler's (highlights that clip);
    the FLIP budget keeps its own lights, as `meshseal embed` measures it."""
    from .. import payload
    from ..api import Watermarker
    from ..mesh import Material, Mesh
    from ..methods.spread import PALETTE_WARNING
    from ..models.spread import palette_share
    from ..reading.registration import pose_error
    from ..render import MeshBatch
    from ..training.views import random_backgrounds
    from ..render.views import sample_views

    was_training = model.training
    model.eval()
    watermarker = Watermarker(model)
    if not watermarker.informed:
        raise ValueError("registration is for informed models")
    calibrated = watermarker.method.calibrated
    coded = calibrated and model.n_bits in payload.SCHEMAS
    generator = torch.Generator().manual_seed(seed + 2_000_003)
    renderer = MeshRenderer()
    count = len(dataset) if n_meshes is None else min(n_meshes, len(dataset))
    rows, pooled = [], []
    attacked = {name: [] for name in attacks or []}
    device = model.device
    for index in range(count):
        item = dataset[index]
        name_of_item = item.get("id", str(index))  # where the rows say which mesh they come from (`by_item`)
        batch = collate([item], device)
        positions, _, uvs, faces = unpadded(batch, 0)  # the mesh's own UV use, before any charts
        palette = palette_share(positions, faces, uvs) >= PALETTE_WARNING
        if calibrated:  # palette faces charted, as `meshseal embed` marks the mesh
            batch = charted_item(batch)
        if coded:
            identity = int(torch.randint(0, 2 ** 31, (1,), generator=generator))
            message = payload.encode(identity, None, model.n_bits)[None].to(device)
            listed = _listed(identity, seed, index, model.n_bits)
        else:
            message = torch.randint(0, 2, (1, model.n_bits), generator=generator).float().to(device)
        positions, normals, uvs, faces, texture = (batch[k] for k in ("positions", "normals", "uvs", "faces", "texture"))
        with torch.no_grad():
            used = batch_texels_used(batch)
            used_strength = None  # learned models have no strength
            if calibrated:  # as `meshseal embed` marks it: within its FLIP budget
                normals_marked, uvs_marked = normals, uvs
                grid = batch_mark_grid(model.texture_encoder, batch)
                cell_width = batch_cell_width(model.texture_encoder, batch)
                mark = lambda at: model.texture_encoder(texture, message, at, payload.key_seed(None), grid, used)  # noqa: E731
                if max_flip is None:
                    texture_marked, used_strength = mark(strength), strength
                else:
                    seen_original, inside = seed_renders(MeshBatch.from_tensors(positions, normals, uvs, faces, texture),
                                                         BUDGET_VIEWS)
                    seen = lambda t: visibility(seen_original, seed_renders(  # noqa: E731
                        MeshBatch.from_tensors(positions, normals, uvs, faces, t), BUDGET_VIEWS)[0], inside)
                    if strength == LOUDEST:  # `embed --strength max`: the loudest within the budgets
                        texture_marked, used_strength, _, _ = strength_filled(mark, seen, max_flip)
                    else:
                        texture_marked, used_strength, _ = strength_within(
                            mark, lambda t: seen(t)["flip_object"], strength, max_flip)
            else:
                normals_marked, uvs_marked, texture_marked = model.embed(positions, normals, uvs, texture, message)
            cameras, lights = sample_views(views, sampler, generator)
            if light_gain != 1.0:
                lights = type(lights)(lights.position, lights.intensity * light_gain)
            background = random_backgrounds(views, generator)
            pictures = renderer(MeshBatch.from_tensors(positions, normals_marked, uvs_marked, faces, texture_marked),
                                cameras, lights, size, size, background).image.clamp(0, 1)
            original = MeshBatch.from_tensors(positions, normals, uvs, faces, texture)
            clean = renderer(original, cameras, lights, size, size, background)  # what the mark changed, as seen
            shown = clean.rgba[..., 3] > 0.5  # the object's pixels
            seen = visibility(clean.image, pictures, shown)
            texture_psnr = float(shown_texture_psnr(texture_marked, texture, used)[0])
            pictures = torch.round(pictures * 255) / 255  # what a saved 8-bit PNG holds
            kinds = (picture_kinds(model.texture_encoder, grid, pictures, shown, cell_width) if calibrated
                     else [["plain"]] * views)
            asset_pictures = {}  # each asset attack's 8-bit pictures, rendered from the attacked marked asset
            marked = Mesh(positions[0], normals_marked[0], faces[0], uvs_marked[0],
                          materials=[Material(texture=texture_marked[0].permute(1, 2, 0))])
            for name in (n for n in attacked if n in ASSET_ATTACKS):
                rng = np.random.default_rng([seed, index, 1_000, attack_stream(name)])
                hit = MeshBatch.from_mesh(attack_asset(name, marked, rng))
                seen_hit = renderer(hit, cameras, lights, size, size, background).image.clamp(0, 1)
                asset_pictures[name] = torch.round(seen_hit * 255) / 255
        readings = []
        for view in range(views):
            picture = pictures[view].permute(1, 2, 0).cpu().numpy()
            started = time.perf_counter()
            known = _read_or_none(watermarker, picture, original, camera=cameras[[view]])
            reading, seconds = known, time.perf_counter() - started
            if register:
                started = time.perf_counter()
                reading = _read_or_none(watermarker, picture, original, register=True)
                reading = None if reading is None else watermarker.look_again(reading, original)  # as `meshseal detect`
                seconds = time.perf_counter() - started
            agree = lambda d: float(np.mean([int(b) for b in d.bits] == message[0].cpu().numpy()))  # noqa: E731
            # A picture `meshseal detect` refuses (e.g. no object found) counts as read at chance.
            found, truth = (None if r is None else watermarker.decide([r]) for r in (reading, known))
            row = {"bit_acc": 0.5 if found is None else agree(found), "bit_acc_known": 0.5 if truth is None else agree(truth),
                   "iou": 0.0 if reading is None or reading.registration_iou is None else reading.registration_iou, "unreadable": reading is None,
                   "pose": math.inf if reading is None else pose_error(original, cameras[[view]], reading.found, size, size),
                   "seconds": seconds}
            if reading is not None:
                readings.append(reading)
            if coded:
                row |= {"detected": found is not None and bool(found.detected),
                        "exact": found is not None and found.message == identity,
                        "wrong": found is not None and found.message not in (None, identity),
                        "named": reading is not None and _named(watermarker.decide([reading], expect=identity)),
                        "listed": reading is not None and _names(watermarker.decide([reading], expect=listed), identity),
                        "detected_known": truth is not None and bool(truth.detected),
                        "exact_known": truth is not None and truth.message == identity,
                        "wrong_known": truth is not None and truth.message not in (None, identity)}
            rows.append(row | {"item": name_of_item, "kinds": kinds[view], "palette": palette, "psnr_object": seen["psnr_object"], "ssim_object": seen["ssim_object"],
                               "flip_object": seen["flip_object"], "psnr_texture_shown": texture_psnr,
                               "strength": used_strength})
            for name in attacked:
                rng = np.random.default_rng([seed, index, view, attack_stream(name)])
                if name in ASSET_ATTACKS:  # the picture of the asset after the attack, in the same view and light
                    hit = asset_pictures[name][view].permute(1, 2, 0).cpu().numpy()
                else:
                    hit = attack_picture(name, np.round(picture * 255).astype(np.uint8), rng).astype(np.float32) / 255.0
                started = time.perf_counter()
                if register:
                    got = _read_or_none(watermarker, hit, original, register=True)
                    got = None if got is None else watermarker.look_again(got, original)
                else:
                    got = _read_or_none(watermarker, hit, original, camera=cameras[[view]])
                decision = None if got is None else watermarker.decide([got])
                seconds = time.perf_counter() - started
                known_hit = None  # registered, the same picture read with its camera too: what registration cost
                camera = cameras[[view]] if not _frame_changed(name) else cropped_camera(name, cameras[[view]], size, size)
                pose = None  # registered: how far the registered camera put the surface from where the known one does
                if register and camera is not None:  # a crop's camera is known too (`attacks.cropped_camera`)
                    known_read = _read_or_none(watermarker, hit, original, camera=camera)
                    known_hit = coded and known_read is not None and bool(watermarker.decide([known_read]).detected)
                    pose = math.inf if got is None else pose_error(original, camera, got.found, *hit.shape[:2])
                attacked[name].append({
                    "detected_known": known_hit, "pose": pose,
                    "item": name_of_item, "kinds": kinds[view],
                    "bit_acc": 0.5 if decision is None else agree(decision),
                    "detected": coded and decision is not None and bool(decision.detected),
                    "exact": coded and decision is not None and decision.message == identity,
                    "wrong": coded and decision is not None and decision.message not in (None, identity),
                    "named": coded and got is not None and _named(watermarker.decide([got], expect=identity)),
                    "listed": coded and got is not None and _names(watermarker.decide([got], expect=listed), identity),
                    "seconds": seconds})
            if log is not None and register:
                log(f"mesh {index + 1}/{count} ({name_of_item}) view {view}: bit_acc {row['bit_acc']:.4f} (known camera "
                    f"{row['bit_acc_known']:.4f}) pose error {row['pose']:.2f} px, IoU {row['iou']:.3f}, {seconds:.1f} s")
        if coded and views > 1:
            decision = watermarker.decide(readings) if readings else None
            pooled.append({"detected": decision is not None and bool(decision.detected),
                           "exact": decision is not None and decision.message == identity})
    model.train(was_training)
    mean = lambda key, table=rows: float(np.mean([r[key] for r in table]))  # noqa: E731
    pose = torch.tensor([r["pose"] for r in rows])
    success = (pose < 0.5) | (torch.tensor([r["iou"] for r in rows]) >= 0.95)
    accuracy = torch.tensor([r["bit_acc"] for r in rows])
    result = {"bit_acc": float(accuracy.mean()), "bit_acc_std": float(accuracy.std()) if len(rows) > 1 else 0.0,
              "bit_acc_known_camera": mean("bit_acc_known"), "psnr_texture_shown": mean("psnr_texture_shown"),
              "psnr_object": mean("psnr_object"), "ssim_object": mean("ssim_object"), "flip_object": mean("flip_object"),
              "flip_object_p95": float(np.nanquantile([r["flip_object"] for r in rows], 0.95)),
              "registration_success": float(success.float().mean()), "registration_iou": mean("iou"),
              # Quantiles count a refused picture as infinitely off; max is over the pictures read; a
              # figure that is not finite is null (JSON has no infinity).
              "pose_error_px": {"median": _finite(pose.nanquantile(0.5)), "p90": _finite(pose.nanquantile(0.9)),
                                "max": _finite(pose[pose.isfinite()].max()) if bool(pose.isfinite().any()) else None},
              "seconds_per_picture": mean("seconds"), "n_meshes": count, "n_views": views, "size": size,
              "n_unreadable": sum(r["unreadable"] for r in rows), "light_gain": light_gain}
    if calibrated and max_flip is not None:
        result |= {"max_flip": max_flip, "strength_mean": mean("strength")}
        if strength == LOUDEST:
            result |= {"strength_asked": LOUDEST,
                       "strength_quantiles": [float(q) for q in np.quantile([r["strength"] for r in rows], [0.1, 0.5, 0.9])]}
        else:
            result["strength_lowered"] = float(np.mean([r["strength"] < strength for r in rows]))
    if calibrated and max_flip is None:
        result |= {"strength_mean": strength}
    if coded:
        result |= {"tpr": mean("detected"), "exact_message": mean("exact"), "tpr_message_named": mean("named"),
                   "tpr_among_listed": mean("listed"),
                   "tpr_known_camera": mean("detected_known"),
                   "exact_message_known_camera": mean("exact_known"), "fpr_threshold": payload.FPR,
                   # a message reported that is not the one marked: the error that matters most to an owner
                   "wrong_message": mean("wrong"), "wrong_message_known_camera": mean("wrong_known")}
    if pooled:
        result |= {"tpr_pooled": mean("detected", pooled), "exact_message_pooled": mean("exact", pooled)}
    if coded:  # meshes with a UV map, and those that use the texture as a palette (`api.PALETTE_WARNING`)
        result["by_uv_map"] = {name: {"pictures": len(part), "bit_acc_known_camera": mean("bit_acc_known", part) if part else None,
                                      "tpr_known_camera": mean("detected_known", part) if part else None,
                                      "psnr_object": mean("psnr_object", part) if part else None,
                                      "flip_object": mean("flip_object", part) if part else None}
                               for name, part in (("uv_mapped", [r for r in rows if not r["palette"]]),
                                                  ("palette", [r for r in rows if r["palette"]]))}
    def split(belongs) -> dict:  # detected as read, and after each attack, of the pictures that `belongs` takes
        part = [r for r in rows if belongs(r)]
        entry = {"pictures": len(part), "detected": mean("detected", part),
                 "detected_known_camera": mean("detected_known", part), "flip_object": mean("flip_object", part)}
        for name, table in attacked.items():
            hit = [r for r in table if belongs(r)]
            entry[name] = mean("detected", hit) if hit else None
            if hit and hit[0]["detected_known"] is not None:  # registered, the same pictures read with their camera
                entry[f"{name}_known_camera"] = mean("detected_known", hit)
                entry[f"{name}_pose_px"] = _median_pose(hit)
        return entry

    if coded:  # by kind of picture (`picture_kinds`)
        names = sorted({kind for r in rows for kind in r["kinds"]}, key=KIND_ORDER.index)
        result["by_kind"] = {kind: split(lambda r, kind=kind: kind in r["kinds"]) for kind in names}
    if coded and by_item:
        result["by_item"] = {name: split(lambda r, name=name: r["item"] == name)
                             for name in dict.fromkeys(r["item"] for r in rows)}
    if attacked:
        result["attacks"] = {name: {"pictures": len(part), "detected": mean("detected", part) if coded else None,
                                    "exact": mean("exact", part) if coded else None,
                                    "wrong": mean("wrong", part) if coded else None,
                                    "named": mean("named", part) if coded else None,
                                    "listed": mean("listed", part) if coded else None, "bit_acc": mean("bit_acc", part),
                                    "seconds": mean("seconds", part)}
                              | ({"detected_known_camera": mean("detected_known", part)}
                                 if coded and part and part[0]["detected_known"] is not None else {})
                              | ({"pose_error_px_median": _median_pose(part)}
                                 if part and part[0]["pose"] is not None else {})
                              for name, part in attacked.items()}
    if not register:  # what is left is the camera-known reading (and its time)
        result = {k: v for k, v in result.items() if k in (
            "bit_acc_known_camera", "tpr_known_camera", "exact_message_known_camera", "wrong_message_known_camera",
            "fpr_threshold", "by_uv_map",
            "tpr_message_named", "tpr_among_listed", "psnr_texture_shown", "psnr_object", "ssim_object", "flip_object", "flip_object_p95", "max_flip", "strength_mean",
            "strength_lowered", "strength_asked", "strength_quantiles", "by_kind", "by_item",
            "seconds_per_picture", "n_meshes", "n_views", "size", "attacks", "light_gain")}
    return result


def _frame_changed(attack: str) -> bool:
    """Whether a picture attack changes the picture's frame (a crop, a screenshot's canvas), so that
    the camera it was rendered with no longer reads it; a resized picture keeps its camera (a camera is
    the same for a picture at any size), as do the asset's attacks and the photometric ones."""
    return attack in GEOMETRIC and not attack.startswith("resize")


def _median_pose(rows: list) -> float | None:
    """The median of the rows' pose errors (px; a refused picture is infinitely off), None if not finite."""
    return _finite(torch.tensor([r["pose"] for r in rows]).nanquantile(0.5))


def _finite(value) -> float | None:
    value = float(value)
    return round(value, 3) if math.isfinite(value) else None


def _read_or_none(watermarker, picture, original, **options):
    """`Watermarker.read`, or None where it refuses the picture with a one-line error."""
    from ..errors import MeshsealError

    try:
        return watermarker.read(picture, original, **options)
    except MeshsealError:
        return None
