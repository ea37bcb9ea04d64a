"""Files written all or nothing, with the permissions the user's umask gives a new file."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from ..errors import MeshError


def file_mode() -> int:
    """The permissions a plainly created file gets: 0666 less the process's umask (a temporary file
    from `tempfile.mkstemp` is 0600 whatever the umask; outputs renamed from one are set to this)."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    umask = os.umask(0o022)  # no /proc: read it by setting it (and put it back at once)
    os.umask(umask)
    return 0o666 & ~umask


def atomic_write_files(files: dict[Path, bytes]) -> None:
    """Write several files all or nothing (as far as a file system allows): each goes to a temporary
    file in its folder first and is renamed into place only once all are written, with the permissions
    the umask gives a new file (`file_mode`). Missing folders are created, and removed again if writing
    fails; no temporary file is left behind."""
    created, temps, current = [], {}, None
    mode = file_mode()
    try:
        for current in files:
            missing = [folder for folder in [current.parent, *current.parent.parents] if not folder.exists()]
            for folder in reversed(missing):
                folder.mkdir()
                created.append(folder)
        for current, data in files.items():
            handle, temps[current] = tempfile.mkstemp(dir=current.parent, prefix=f".{current.name}.", suffix=".tmp")
            os.fchmod(handle, mode)
            with os.fdopen(handle, "wb") as stream:
                stream.write(data)
        for current, temp in temps.items():
            os.replace(temp, current)
    except BaseException as error:
        for temp in temps.values():
            if os.path.exists(temp):
                os.unlink(temp)
        for folder in reversed(created):
            try:
                folder.rmdir()
            except OSError:
                pass
        if isinstance(error, OSError):
            raise MeshError(f"{current}: cannot write: {error.strerror or error}") from None
        raise


def atomic_write(path: Path, data: bytes) -> None:
    """Write `data` to `path` through a temporary file in the same folder and a rename (see
    `atomic_write_files`)."""
    atomic_write_files({Path(path): data})
