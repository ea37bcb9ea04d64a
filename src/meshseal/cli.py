"""The `meshseal` command line: one subcommand per module, errors as one line on stderr.

Each subcommand lives in a module with `register(subparsers)`; that function adds its parser and sets
`func=callable(args) -> int | None`. Modules that do not exist (yet) are skipped, so optional parts
of the package can add commands without touching this file.

Exit codes: 0 success, 1 the command reported failure (detect: no mark detected), 2 bad input or
arguments, 130 interrupted.
Set MESHSEAL_DEBUG=1 to get the full traceback instead of the one-line error. Before a command runs, the
thread policy of `meshseal.threads` is applied (MESHSEAL_THREADS=N sets the count).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import os
import sys

from . import __version__
from .errors import MeshsealError

# Subcommand modules, in the order they appear in --help.
COMMAND_MODULES = (
    "meshseal.commands.render",
    "meshseal.commands.info",
    "meshseal.data.cli",
    "meshseal.commands.model",
)


EPILOG = """example (mark a mesh, picture it, read the mark back from the picture):
  meshseal embed chair.obj -o chair_marked.obj --message ab42 --key SECRET --preview sheet.png
  meshseal render chair_marked.obj -o view.png          # or any screenshot or photo of it
  meshseal detect view.png --mesh chair.obj --key SECRET
    view.png: detected "ab42" (p = 4.5e-94, camera: metadata)

'meshseal COMMAND --help' gives each command's options. Exit status: 0 success (detect: a mark
detected), 1 detect found no mark, 2 an error (one 'meshseal: error:' line), 130 interrupted."""


class UsageError(MeshsealError):
    """Bad command-line arguments."""


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (plus a pointer to --help) instead of usage + error."""

    def error(self, message):
        raise UsageError(f"{message} (see '{self.prog} --help')")


def _module_exists(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):  # a missing parent package
        return False


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="meshseal", description="Invisible watermarks in textured 3D meshes, "
                     "read back from 2D renderings.", epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"meshseal {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name in COMMAND_MODULES:
        if _module_exists(name):
            importlib.import_module(name).register(subparsers)
    return parser


def _one_line(error: BaseException) -> str:
    if isinstance(error, OSError) and error.strerror:
        where = f"{error.filename}: " if error.filename else ""
        text = f"{where}{error.strerror}"
    else:
        text = str(error) or type(error).__name__
    lines = [line.strip() for line in text.strip().splitlines() if line.strip()]
    return lines[0] if lines else type(error).__name__


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit code (the console script exits with it)."""
    debug = os.environ.get("MESHSEAL_DEBUG", "") not in ("", "0")
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        if getattr(args, "func", None) is None:
            parser.print_help(sys.stderr)
            return 2
        from .threads import configure

        configure()  # thread counts and passive waits, before the command imports torch or numba
        result = args.func(args)
        return int(result or 0)
    except SystemExit as exit_:  # --help, --version
        return exit_.code if isinstance(exit_.code, int) else (0 if exit_.code is None else 2)
    except KeyboardInterrupt:
        print("meshseal: interrupted", file=sys.stderr)
        return 130
    except (MeshsealError, OSError, ValueError) as error:
        if debug:
            raise
        print(f"meshseal: error: {_one_line(error)}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
