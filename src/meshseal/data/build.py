"""`meshseal data build`: assets -> fixed-size items, a texture pool, a manifest and a grouped split.

Layout of a built dataset DIR:
    meshes/<id>.npz            positions (Vmax,3) f32 in [-1,1] Z-up, normals, uvs (Vmax,2), faces (Fmax,3) i32
                               (padding faces are [0,0,0]), n_verts, n_faces, meta (JSON string)
    textures/<id>.png          the item's texture, T x T RGB
    textures/pool/<n>.png      real texture images (2T x 2T) for 'real' textures and on-the-fly re-texturing
    textures/pool.jsonl        provenance of each pool image
    manifest.jsonl / .csv      one row per item (id, split, source, version, original path, category, ...)
    splits/{train,test,test_cc0}.txt
    build_config.json, build_report.json, failed.jsonl
Resumable: items whose npz + png exist and load are kept; failed assets are listed and not retried
(unless --retry-failed).
"""

from __future__ import annotations

import csv
import json
import multiprocessing
import os
import sys
import time
import zipfile
import zlib
from collections import Counter, defaultdict
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from dataclasses import asdict
from pathlib import Path


import numpy as np
from PIL import Image

from ..errors import MeshError, MeshsealError
from ..threads import configure as configure_threads
from . import sources as S
from .formats import MESH_SUFFIXES, RawMesh, read_image, read_mesh
from .process import ProcessOptions, process_mesh, resize

# Workers are spawned, not forked: a fork after torch/numba started their threads can deadlock.
_SPAWN = multiprocessing.get_context("spawn")
# One thread a worker, set before it imports torch or numba (meshseal.threads): the pool has a worker per core.
_ONE_THREAD = {"initializer": configure_threads, "initargs": (None, True)}


class _InProcess:
    """The part of an executor `build` uses, run in this process (`workers=0`): no start-up of a
    worker (a spawned worker imports torch again), tracebacks where they happen; a crash ends the build."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        return None

    def submit(self, fn, *args) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args))
        except Exception as error:  # noqa: BLE001  (what a worker's future would carry)
            future.set_exception(error)
        return future

    def map(self, fn, *iterables, chunksize: int = 1):
        return map(fn, *iterables)


def _executor(workers: int):
    """`workers` spawned one-thread processes, or this process for 0."""
    if int(workers) <= 0:
        return _InProcess()
    return ProcessPoolExecutor(max_workers=int(workers), mp_context=_SPAWN, **_ONE_THREAD)

FORMAT_VERSION = 1
CC0 = {"CC0-1.0", "CC0", "public-domain"}
MANIFEST_FIELDS = ["id", "split", "source", "source_version", "original_path", "name", "category",
                   "source_category", "creator", "license", "group", "n_verts", "n_faces", "orig_verts",
                   "orig_faces", "texture_kind", "texture_source", "publishable", "file", "texture_file"]


def item_rng(seed: int, key: str) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), zlib.crc32(key.encode())]))


def _atomic_bytes(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _png_bytes(image: np.ndarray) -> bytes:
    import io
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="PNG")
    return buffer.getvalue()


def item_is_valid(out: Path, asset_id: str) -> dict | None:
    """The stored meta of a finished item, or None if it is missing or unreadable."""
    npz, png = out / "meshes" / f"{asset_id}.npz", out / "textures" / f"{asset_id}.png"
    if not (npz.is_file() and png.is_file()):
        return None
    try:
        with np.load(npz) as data:
            meta = json.loads(str(data["meta"]))
            if data["positions"].shape[1] != 3:
                return None
        return meta
    except Exception:
        return None


# ------------------------------------------------------------------ workers (run in subprocesses)

_ZIPS: dict[str, zipfile.ZipFile] = {}


def _candidate_bytes(candidate: dict) -> bytes:
    if candidate["archive"]:
        archive = _ZIPS.get(candidate["archive"])
        if archive is None:
            archive = _ZIPS[candidate["archive"]] = zipfile.ZipFile(candidate["archive"])
        return archive.read(candidate["member"])
    return Path(candidate["member"]).read_bytes()


def pool_worker(candidate: dict, size: int) -> tuple[np.ndarray | None, str]:
    """Decode a texture candidate, reject tiny or flat images, centre-crop and resize to size x size."""
    try:
        image = read_image(_candidate_bytes(candidate), candidate["original_path"], alpha="drop")
    except (MeshError, OSError, KeyError, zipfile.BadZipFile) as error:
        return None, str(error)
    h, w = image.shape[:2]
    if min(h, w) < 64:
        return None, "too small"
    if max(h, w) > 2.5 * min(h, w):
        return None, "too elongated"
    if image.astype(np.float32).std() < 10.0:
        return None, "nearly uniform"
    side = min(h, w)
    top, left = (h - side) // 2, (w - side) // 2
    return resize(np.ascontiguousarray(image[top:top + side, left:left + side]), size, size), ""


def mesh_worker(asset: dict, options: dict, out: str, pool: list[str], seed: int) -> tuple[str, dict | None, str]:
    """Load, process and store one asset. Returns (id, meta, error)."""
    asset_id = asset["id"]
    try:
        raw: RawMesh = read_mesh(asset["path"], [Path(p) for p in asset.get("search_roots") or []],
                                 texture_path=asset.get("texture_path"))
        if asset.get("rotation"):
            rotation = np.asarray(asset["rotation"], dtype=np.float64).reshape(3, 3)
            raw.positions = raw.positions @ rotation.T
        orig_verts, orig_faces = len(raw.positions), len(raw.faces)
        item = process_mesh(raw, ProcessOptions(**options), item_rng(seed, asset_id), pool)
    except MeshsealError as error:
        return asset_id, None, str(error).splitlines()[0][:300]
    except MemoryError:
        return asset_id, None, "out of memory"
    except Exception as error:  # a bad asset must never stop the build
        return asset_id, None, f"{type(error).__name__}: {str(error).splitlines()[0][:200] if str(error) else ''}"
    out = Path(out)
    meta = {k: asset[k] for k in ("id", "source", "source_version", "original_path", "name", "category",
                                  "source_category", "creator", "license", "group")}
    texture_source = item.texture_source
    if item.texture_kind == "real":
        texture_source = f"pool/{Path(texture_source).name}"
    meta.update(n_verts=int(item.n_verts), n_faces=int(item.n_faces), orig_verts=int(orig_verts),
                orig_faces=int(orig_faces), texture_kind=item.texture_kind, texture_source=texture_source,
                file=f"meshes/{asset_id}.npz", texture_file=f"textures/{asset_id}.png")
    import io
    buffer = io.BytesIO()
    np.savez_compressed(buffer, positions=item.positions, normals=item.normals, uvs=item.uvs, faces=item.faces,
                        n_verts=np.int32(item.n_verts), n_faces=np.int32(item.n_faces),
                        meta=np.array(json.dumps(meta)))
    _atomic_bytes(out / "textures" / f"{asset_id}.png", _png_bytes(item.texture))
    _atomic_bytes(out / "meshes" / f"{asset_id}.npz", buffer.getvalue())
    return asset_id, meta, ""


# ------------------------------------------------------------------ split


def assign_split(assets: list[S.Asset], seed: int, test_fraction: float, cc0_test_fraction: float = 0.5
                 ) -> dict[str, str]:
    """train/test by whole groups (catalog/creator/folder), never at random per item.

    Items with a split hint (a train/ or test/ folder, as in ModelNet) keep it. CC0 groups are drawn
    first until about `cc0_test_fraction` of the CC0 items are in test (that subset may be published),
    then other groups until `test_fraction` of all items. Groups larger than 8% of all items stay in train.
    """
    split: dict[str, str] = {}
    free = [a for a in assets if a.split_hint not in ("train", "test")]
    for a in assets:
        if a.split_hint in ("train", "test"):
            split[a.id] = a.split_hint
    groups: dict[str, list[S.Asset]] = defaultdict(list)
    for a in free:
        groups[a.group].append(a)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7]))
    keys = sorted(groups)
    order = [keys[i] for i in rng.permutation(len(keys))]
    n_total = len(assets)
    target = int(round(test_fraction * n_total)) - sum(1 for v in split.values() if v == "test")
    max_group = max(1, int(0.08 * n_total))
    chosen: set[str] = set()

    def is_cc0(group):
        return all(a.license in CC0 for a in groups[group])

    n_cc0 = sum(len(groups[g]) for g in keys if is_cc0(g))
    cc0_target = int(round(cc0_test_fraction * n_cc0))
    count = cc0_count = 0
    for g in order:
        if is_cc0(g) and cc0_count < cc0_target and len(groups[g]) <= max_group and count < target:
            chosen.add(g)
            cc0_count += len(groups[g])
            count += len(groups[g])
    for g in order:
        if g in chosen or is_cc0(g) or len(groups[g]) > max_group:
            continue
        if count >= target:
            break
        if count + len(groups[g]) > target + max(2, 0.02 * n_total):
            continue  # would overshoot: try a smaller group
        chosen.add(g)
        count += len(groups[g])
    for g, items in groups.items():
        for a in items:
            split[a.id] = "test" if g in chosen else "train"
    return split


# ------------------------------------------------------------------ the build


def _log(message: str) -> None:
    print(f"meshseal: {message}", file=sys.stderr, flush=True)


def _progress(total: int, desc: str):
    from tqdm import tqdm
    interactive = sys.stderr.isatty()
    return tqdm(total=total, desc=desc, file=sys.stderr, mininterval=0.5 if interactive else 10.0,
                dynamic_ncols=interactive, ascii=not interactive)


def gather(sources: list[str], texture_sources: list[str], cache: Path, from_folder: Path | None,
           textures_dir: Path | None, license_: str, creator: str):
    assets: list[S.Asset] = []
    candidates: list[S.TextureCandidate] = []
    problems: list[str] = []
    if from_folder is not None:
        assets += S.folder_source(from_folder, license_, creator)
        if not assets:
            raise S.DataError(f"{from_folder}: no mesh files found ({', '.join(sorted(MESH_SUFFIXES))})")
    sh3d_textures: list[S.TextureCandidate] = []
    for name in sources:
        if name not in S.MESH_SOURCES:
            raise S.DataError(f"unknown source '{name}' (known: {', '.join(S.MESH_SOURCES)})")
        try:
            found, textures = S.MESH_SOURCES[name](cache, _log)
        except S.DataError as error:
            S.warn(str(error))
            problems.append(str(error))
            continue
        _log(f"source {name}: {len(found)} meshes")
        assets += found
        if name == "sweethome3d":
            sh3d_textures = textures
    for name in texture_sources:
        try:
            if name == "sweethome3d":
                if not sh3d_textures and "sweethome3d" not in sources:
                    _, sh3d_textures = S.sweethome3d_source(cache, _log)
                found = sh3d_textures
            elif name in S.TEXTURE_PACKAGES:
                _, found = S.texture_package_source(name, cache, _log)
            else:
                raise S.DataError(f"unknown texture source '{name}' (known: "
                                  f"{', '.join(list(S.TEXTURE_PACKAGES) + ['sweethome3d'])})")
        except S.DataError as error:
            if "unknown texture source" in str(error):
                raise
            S.warn(str(error))
            problems.append(str(error))
            continue
        _log(f"texture source {name}: {len(found)} candidate images")
        candidates += found
    if textures_dir is not None:
        candidates += S.image_folder_textures(textures_dir, license_)
    # unique ids
    seen: Counter = Counter()
    for a in assets:
        seen[a.id] += 1
        if seen[a.id] > 1:
            a.id = f"{a.id}-{seen[a.id]}"
    return assets, candidates, problems


def build_pool(out: Path, candidates: list[S.TextureCandidate], size: int, pool_size: int, seed: int,
               workers: int) -> list[dict]:
    """Pick up to pool_size usable real images (seeded order, balanced across sources)."""
    pool_dir = out / "textures" / "pool"
    pool_dir.mkdir(parents=True, exist_ok=True)
    index_file = out / "textures" / "pool.jsonl"
    if index_file.is_file():
        rows = [json.loads(line) for line in index_file.read_text().splitlines() if line.strip()]
        if all((out / r["file"]).is_file() for r in rows):
            return rows
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 11]))
    by_source: dict[str, list] = defaultdict(list)
    for c in candidates:
        by_source[c.source].append(c)
    queues = []
    for source in sorted(by_source):
        items = by_source[source]
        queues.append([items[i] for i in rng.permutation(len(items))])
    ordered = []  # round-robin across sources so that every source is represented
    for k in range(max((len(q) for q in queues), default=0)):
        ordered += [q[k] for q in queues if k < len(q)]
    rows: list[dict] = []
    start = 0
    progress = _progress(min(pool_size, len(ordered)), "texture pool")
    with _executor(workers) as executor:
        while len(rows) < pool_size and start < len(ordered):
            chunk = ordered[start:start + max(32, int((pool_size - len(rows)) * 1.3))]
            start += len(chunk)
            results = list(executor.map(pool_worker, [asdict(c) for c in chunk], [size] * len(chunk),
                                        chunksize=8))
            for candidate, (image, _reason) in zip(chunk, results):
                if image is None or len(rows) >= pool_size:
                    continue
                name = f"{len(rows):05d}.png"
                _atomic_bytes(pool_dir / name, _png_bytes(image))
                rows.append({"file": f"textures/pool/{name}", "source": candidate.source,
                             "source_version": candidate.source_version, "license": candidate.license,
                             "original_path": candidate.original_path})
                progress.update(1)
    progress.close()
    index_file.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return rows


def build(out, *, sources=S.DEFAULT_SOURCES, texture_sources=S.DEFAULT_TEXTURE_SOURCES, from_folder=None,
          textures_dir=None, cache=None, seed: int = 0, n_faces: int = 5000, max_verts: int | None = None,
          texture_size: int = 128, pool_size: int = 1000, test_fraction: float = 0.15, p_noise: float = 0.5,
          workers: int = 2, max_per_source: int | None = None, limit: int | None = None,
          retry_failed: bool = False, license_: str = "unknown", creator: str = "unknown") -> dict:
    """Build (or resume) a dataset in `out`; returns the build report."""
    started = time.time()
    out = Path(out)
    cache = Path(cache) if cache else Path.home() / ".cache" / "meshseal" / "debs"
    max_verts = int(max_verts or n_faces)
    if n_faces < 4 or texture_size < 8 or max_verts < 4:
        raise S.DataError("--faces must be >= 4, --vmax >= 4 and --texture-size >= 8")
    if not 0.0 <= test_fraction < 1.0:
        raise S.DataError("--test-fraction must be in [0, 1)")
    config = {"format": FORMAT_VERSION, "seed": int(seed), "n_faces": int(n_faces), "max_verts": max_verts,
              "texture_size": int(texture_size), "pool_texture_size": 2 * int(texture_size),
              "p_noise": float(p_noise)}
    out.mkdir(parents=True, exist_ok=True)
    config_file = out / "build_config.json"
    if config_file.is_file():
        previous = json.loads(config_file.read_text())
        if {k: previous.get(k) for k in config} != config:
            raise S.DataError(f"{out} was built with other settings ({previous}); use another --out or delete it")
    for sub in ("meshes", "textures", "splits"):
        (out / sub).mkdir(exist_ok=True)

    assets, candidates, problems = gather(list(sources or []), list(texture_sources or []), cache,
                                          Path(from_folder) if from_folder else None,
                                          Path(textures_dir) if textures_dir else None, license_, creator)
    if max_per_source:
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 13]))
        by_source: dict[str, list] = defaultdict(list)
        for a in assets:
            by_source[a.source].append(a)
        assets = []
        for source in sorted(by_source):
            items = by_source[source]
            if len(items) > max_per_source:
                keep = sorted(rng.choice(len(items), max_per_source, replace=False))
                items = [items[i] for i in keep]
            assets += items
    if limit:
        assets = assets[:limit]
    if not assets:
        raise S.DataError("no assets to build (all sources failed or are empty)")
    config["sources"] = sorted({a.source for a in assets})
    config_file.write_text(json.dumps(config, indent=1) + "\n")

    split = assign_split(assets, seed, test_fraction)
    pool_rows = build_pool(out, candidates, 2 * texture_size, pool_size, seed, workers) if candidates else []
    pool_paths = [str(out / r["file"]) for r in pool_rows]
    if not pool_paths and p_noise < 1.0:
        S.warn("no real texture images: meshes without their own texture get noise textures")

    failed_file = out / "failed.jsonl"
    failed: dict[str, str] = {}
    if failed_file.is_file() and not retry_failed:
        for line in failed_file.read_text().splitlines():
            if line.strip():
                row = json.loads(line)
                failed[row["id"]] = row["error"]
    metas: dict[str, dict] = {}
    todo = []
    for a in assets:
        meta = item_is_valid(out, a.id)
        if meta is not None:
            metas[a.id] = meta
        elif a.id not in failed:
            todo.append(a)
    resumed = len(metas)
    _log(f"{len(assets)} assets: {resumed} already built, {len([a for a in assets if a.id in failed])} "
         f"failed before, {len(todo)} to build with {workers} worker(s)")
    options = {"n_faces": int(n_faces), "max_verts": max_verts, "texture_size": int(texture_size),
               "p_noise": float(p_noise)}
    new_failures: dict[str, str] = {}
    if todo:
        progress = _progress(len(todo), "meshes")
        with _executor(workers) as executor, \
                open(failed_file, "a") as failed_log:
            futures = [executor.submit(mesh_worker, a.to_dict(), options, str(out), pool_paths, seed) for a in todo]
            for future in as_completed(futures):
                try:
                    asset_id, meta, error = future.result()
                except Exception as crash:  # a worker died (e.g. killed): count, go on
                    asset_id, meta, error = "?", None, f"worker crashed: {crash}"
                if meta is not None:
                    metas[asset_id] = meta
                else:
                    new_failures[asset_id] = error
                    failed_log.write(json.dumps({"id": asset_id, "error": error}) + "\n")
                    failed_log.flush()
                progress.update(1)
                progress.set_postfix(ok=len(metas), skipped=len(new_failures) + len(failed), refresh=False)
        progress.close()
    failed.update(new_failures)

    rows = []
    for a in assets:
        meta = metas.get(a.id)
        if meta is None:
            continue
        row = dict(meta)
        row["split"] = split[a.id]
        row["publishable"] = row["split"] == "test" and row["license"] in CC0
        rows.append(row)
    write_manifest(out, rows)
    ids = {a.id for a in assets}
    reasons = Counter(_reason(e) for i, e in failed.items() if i in ids)
    report = {
        "n_assets": len(assets), "n_built": len(rows), "n_skipped": len(assets) - len(rows),
        "n_resumed": resumed, "skip_reasons": dict(reasons.most_common()), "n_textures": len(pool_rows),
        "source_problems": problems, "seconds": round(time.time() - started, 1),
    }
    (out / "build_report.json").write_text(json.dumps(report, indent=1) + "\n")
    _log(f"built {len(rows)} items ({report['n_skipped']} skipped) in {report['seconds']} s -> {out}")
    return report


def _reason(error: str) -> str:
    import re

    text = error.split(": ", 1)[-1] if error.startswith("/") else error
    return re.sub(r"\d+", "N", text.split("(")[0].strip())[:80]


def write_manifest(out: Path, rows: list[dict]) -> None:
    rows = sorted(rows, key=lambda r: r["id"])
    _atomic_bytes(out / "manifest.jsonl", "".join(json.dumps({k: r.get(k) for k in MANIFEST_FIELDS}) + "\n"
                                                   for r in rows).encode())
    import io
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=MANIFEST_FIELDS, extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    _atomic_bytes(out / "manifest.csv", text.getvalue().encode())
    (out / "splits").mkdir(exist_ok=True)
    for name, keep in (("train", lambda r: r["split"] == "train"), ("test", lambda r: r["split"] == "test"),
                       ("test_cc0", lambda r: r["publishable"])):
        _atomic_bytes(out / "splits" / f"{name}.txt", "".join(r["id"] + "\n" for r in rows if keep(r)).encode())


def read_manifest(root) -> list[dict]:
    path = S.manifest_path(root)
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def dataset_stats(root) -> dict:
    root = Path(root)
    rows = read_manifest(root)
    pool_file = root / "textures" / "pool.jsonl"
    pool = [json.loads(l) for l in pool_file.read_text().splitlines() if l.strip()] if pool_file.is_file() else []
    report = json.loads((root / "build_report.json").read_text()) if (root / "build_report.json").is_file() else {}
    config = json.loads((root / "build_config.json").read_text()) if (root / "build_config.json").is_file() else {}

    def count(key, subset=rows):
        return dict(sorted(Counter(str(r[key]) for r in subset).items(), key=lambda kv: (-kv[1], kv[0])))

    train = [r for r in rows if r["split"] == "train"]
    test = [r for r in rows if r["split"] == "test"]
    return {
        "n_items": len(rows), "n_train": len(train), "n_test": len(test),
        "n_test_cc0": sum(1 for r in rows if r.get("publishable")),
        "n_textures": len(pool), "n_own_textures": sum(1 for r in rows if r["texture_kind"] == "own"),
        "n_categories": len({r["category"] for r in rows}),
        "n_skipped": report.get("n_skipped", 0), "skip_reasons": report.get("skip_reasons", {}),
        "build_seconds": report.get("seconds"),
        "faces": config.get("n_faces"), "max_verts": config.get("max_verts"),
        "texture_size": config.get("texture_size"),
        "split": {"train": len(train), "test": len(test)},
        "category": count("category"), "category_train": count("category", train),
        "category_test": count("category", test), "source": count("source"), "license": count("license"),
        "texture_kind": count("texture_kind"),
        "texture_pool_source": dict(Counter(r["source"] for r in pool)),
        "texture_pool_license": dict(Counter(r["license"] for r in pool)),
        "mean_verts": round(float(np.mean([r["n_verts"] for r in rows])), 1) if rows else 0,
        "mean_faces": round(float(np.mean([r["n_faces"] for r in rows])), 1) if rows else 0,
    }


def format_stats(stats: dict) -> str:
    lines = [f"items: {stats['n_items']}  train: {stats['n_train']}  test: {stats['n_test']}  "
             f"(CC0 test subset: {stats['n_test_cc0']})  skipped: {stats['n_skipped']}",
             f"real texture images in pool: {stats['n_textures']}  items with own texture: {stats['n_own_textures']}"
             f"  categories: {stats['n_categories']}",
             f"faces <= {stats['faces']}, vertices <= {stats['max_verts']}, texture {stats['texture_size']}^2; "
             f"mean {stats['mean_verts']} vertices, {stats['mean_faces']} faces"]
    for key in ("source", "license", "texture_kind", "texture_pool_source", "category"):
        width = max((len(k) for k in stats[key]), default=0)
        lines.append(f"{key}:")
        for name, n in stats[key].items():
            extra = ""
            if key == "category":
                extra = f"  (train {stats['category_train'].get(name, 0)}, test {stats['category_test'].get(name, 0)})"
            lines.append(f"  {name:<{width}}  {n:>6}{extra}")
    if stats["skip_reasons"]:
        lines.append("skipped because:")
        for reason, n in stats["skip_reasons"].items():
            lines.append(f"  {n:>5}  {reason}")
    return "\n".join(lines)
