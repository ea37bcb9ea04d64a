"""`meshseal data build` and `meshseal data stats`.

The main CLI calls `register(subparsers)`; `python -m meshseal.data.cli ...` runs the same commands alone.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..errors import MeshsealError
from . import sources as S


def _list(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()] if text and text.lower() != "none" else []


def cmd_build(args) -> int:
    for folder in (args.from_folder, args.textures):  # a mistyped folder answered before the heavy imports
        if folder is not None:
            S.existing_folder(folder)
    from .build import build, dataset_stats

    sources = _list(args.sources) if args.sources is not None else \
        ([] if args.from_folder else list(S.DEFAULT_SOURCES))
    texture_sources = _list(args.texture_sources) if args.texture_sources is not None else \
        ([] if args.from_folder else list(S.DEFAULT_TEXTURE_SOURCES))
    build(args.out, sources=sources, texture_sources=texture_sources, from_folder=args.from_folder,
          textures_dir=args.textures, cache=args.cache, seed=args.seed, n_faces=args.faces,
          max_verts=args.vmax, texture_size=args.texture_size, pool_size=args.pool_size,
          test_fraction=args.test_fraction, p_noise=args.p_noise, workers=args.workers,
          max_per_source=args.max_per_source, limit=args.limit, retry_failed=args.retry_failed,
          license_=args.license, creator=args.creator)
    stats = dataset_stats(args.out)
    print(json.dumps({k: stats[k] for k in ("n_train", "n_test", "n_test_cc0", "n_textures", "n_categories",
                                            "n_skipped", "build_seconds")}))
    return 0


def cmd_stats(args) -> int:
    S.manifest_path(args.dir)  # not a dataset: answered before the heavy imports
    from .build import dataset_stats, format_stats

    stats = dataset_stats(args.dir)
    print(json.dumps(stats, indent=None if args.json else 1) if args.json else format_stats(stats))
    return 0


def register(subparsers) -> argparse.ArgumentParser:
    """Add the `data` command (with `build` and `stats`) to a parent CLI's subparsers."""
    data = subparsers.add_parser("data", help="build and inspect training/test data",
                                 description="Build training and test data from real 3D assets.")
    sub = data.add_subparsers(dest="data_command", metavar="{build,stats}")
    sub.required = True

    b = sub.add_parser("build", help="fetch assets (Debian packages) or read a folder and write a dataset",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    b.add_argument("--out", required=True, type=Path, help="dataset folder to write (resumable)")
    b.add_argument("--from-folder", type=Path, default=None,
                   help="build from your own meshes (e.g. ModelNet40: category folders, train/test subfolders)")
    b.add_argument("--sources", default=None,
                   help=f"Debian mesh sources, comma-separated (default: {','.join(S.DEFAULT_SOURCES)}; "
                        f"none with --from-folder)")
    b.add_argument("--texture-sources", default=None,
                   help=f"real texture sources (default: {','.join(S.DEFAULT_TEXTURE_SOURCES)}; none with "
                        f"--from-folder)")
    b.add_argument("--textures", type=Path, default=None, help="a folder of texture images for the pool")
    b.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "meshseal" / "debs",
                   help="download and unpack cache")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--faces", type=int, default=5000, help="face count per mesh (padded)")
    b.add_argument("--vmax", type=int, default=None, help="vertex cap per mesh (default: = --faces)")
    b.add_argument("--texture-size", type=int, default=128)
    b.add_argument("--pool-size", type=int, default=1000, help="real texture images to keep")
    b.add_argument("--test-fraction", type=float, default=0.15)
    b.add_argument("--p-noise", type=float, default=0.5,
                   help="meshes without a texture: probability of noise (else a real image)")
    b.add_argument("--workers", type=int, default=2, help="worker processes (0: build in this process)")
    b.add_argument("--max-per-source", type=int, default=None, help="at most this many meshes per source")
    b.add_argument("--limit", type=int, default=None, help="at most this many meshes (quick trials)")
    b.add_argument("--retry-failed", action="store_true", help="retry assets that failed in an earlier run")
    b.add_argument("--license", default="unknown", help="license recorded for --from-folder items")
    b.add_argument("--creator", default="unknown", help="creator recorded for --from-folder items")
    b.set_defaults(func=_guarded(cmd_build))

    s = sub.add_parser("stats", help="counts per split, category, source, license and texture kind")
    s.add_argument("dir", type=Path)
    s.add_argument("--json", action="store_true", help="one JSON object")
    s.set_defaults(func=_guarded(cmd_stats))
    return data


def _guarded(command):
    """Wrap a command: bad input -> one line on stderr and exit code 2, no traceback."""

    def call(args) -> int:
        return _run(command, args)

    call.__name__ = command.__name__
    return call


def run(args) -> int:
    return int(args.func(args) or 0)


def _run(command, args) -> int:
    try:
        return int(command(args) or 0)
    except MeshsealError as error:
        print(f"meshseal: error: {error}", file=sys.stderr)
        return 2
    except OSError as error:
        print(f"meshseal: error: {error.strerror or error}: {error.filename or ''}".rstrip(": "), file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("meshseal: interrupted (run the same command again to resume)", file=sys.stderr)
        return 130


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="meshseal")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
