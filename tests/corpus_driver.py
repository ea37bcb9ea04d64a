"""Run many corpus runs (see corpus_gen.py) in one process: `python corpus_driver.py RUNS.json LIMIT`.

For each run: hash every regular file of its input folder, call `meshseal.cli.main(argv)` with stdout and
stderr captured, under an alarm of LIMIT seconds (a blocking open of a pipe is interrupted by it), then
hash again and list what is left in its output folder. Prints one JSON line per run, as it goes, so the
test still learns which run hung if the whole process has to be killed.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import signal
import stat
import sys
import time
import traceback
from pathlib import Path


class _Timeout(BaseException):
    pass


def _on_alarm(signum, frame):
    raise _Timeout()


def snapshot(folder: Path) -> dict[str, str]:
    """relative path -> sha256 for regular files, the file type for anything else (never opened)."""
    result = {}
    for path in sorted(folder.rglob("*")) if folder.exists() else []:
        mode = path.lstat().st_mode
        name = str(path.relative_to(folder))
        if stat.S_ISREG(mode):
            result[name] = hashlib.sha256(path.read_bytes()).hexdigest()
        else:
            result[name] = f"mode {stat.S_IFMT(mode):o}" + (f" -> {os.readlink(path)}" if stat.S_ISLNK(mode) else "")
    return result


def main() -> None:
    import torch

    torch.set_num_threads(1)
    from meshseal.cli import main as meshseal

    runs = json.loads(Path(sys.argv[1]).read_text())
    limit = int(sys.argv[2])
    signal.signal(signal.SIGALRM, _on_alarm)
    os.environ.pop("MESHSEAL_DEBUG", None)
    for run in runs:
        watch, out = Path(run["watch"]), Path(run["out"])
        before = snapshot(watch)
        stdout, stderr = io.StringIO(), io.StringIO()
        started = time.monotonic()
        code, crash = None, None
        signal.alarm(limit)
        try:
            with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
                code = meshseal(run["argv"])
        except _Timeout:
            crash = f"timed out after {limit} s"
        except BaseException:  # anything escaping main() is a traceback the user would see
            crash = traceback.format_exc()
        finally:
            signal.alarm(0)
        seconds = time.monotonic() - started
        print(json.dumps({"id": run["id"], "code": code, "crash": crash, "stdout": stdout.getvalue(),
                          "stderr": stderr.getvalue(), "seconds": round(seconds, 3),
                          "changed": snapshot(watch) != before, "left": sorted(snapshot(out))}), flush=True)


if __name__ == "__main__":
    main()
