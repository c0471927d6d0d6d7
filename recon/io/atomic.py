"""Atomic file writes: write a temporary file in the target's folder, then os.replace it.

os.replace is atomic on POSIX and Windows when source and target lie on the same file system,
which is why the temporary file is created in the target's own folder (not in /tmp). A reader
therefore sees either the old file or the complete new one, never a half-written file, and a
crash mid-write leaves at most a hidden `.NAME.*.tmp.EXT` file behind.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from recon.errors import ReconError, WriteError, describe_os_error


def _process_umask() -> int:
    """The process umask, read without changing it (os.umask would race with other threads)."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    return 0o022


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to `path`; on success move it onto `path` atomically.

    The temporary name keeps the target's extension (`.NAME.RANDOM.tmp.EXT`) because some writers
    (trimesh, Pillow) choose the format from it. The parent folder is created when missing. If the
    body raises, the temporary file is removed and `path` is left untouched.

    Usage:
        with atomic_path("out/image.png") as temporary:
            write_something(temporary)
    """
    target = Path(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        handle, name = tempfile.mkstemp(
            dir=target.parent, prefix=f".{target.stem}.", suffix=f".tmp{target.suffix}"
        )
    except OSError as error:
        raise WriteError(f"cannot write {describe_os_error(error, target)}") from error
    os.close(handle)
    temporary = Path(name)
    try:
        yield temporary
        if not temporary.exists():
            raise ReconError(f"{target}: the writer did not create the temporary file {temporary}")
        # Flush the data to disk before the rename so that a crash cannot leave an empty target.
        with open(temporary, "rb") as written:
            os.fsync(written.fileno())
        # mkstemp creates files with mode 0600; give the file the mode a plain open() would.
        os.chmod(temporary, 0o666 & ~_process_umask())
        os.replace(temporary, target)
    except OSError as error:
        temporary.unlink(missing_ok=True)
        raise WriteError(f"cannot write {describe_os_error(error, target)}") from error
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write bytes to `path` atomically."""
    with atomic_path(path) as temporary:
        temporary.write_bytes(data)


def atomic_write_text(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> None:
    """Write text to `path` atomically."""
    with atomic_path(path) as temporary:
        temporary.write_text(text, encoding=encoding)


def atomic_write_json(path: str | os.PathLike, data: Any, indent: int | None = 2) -> None:
    """Write `data` as JSON (with a trailing newline) to `path` atomically.

    NaN and infinity are refused (ReconError naming the path): they are not valid JSON and most
    readers other than Python's would reject the file.
    """
    try:
        text = json.dumps(data, indent=indent, allow_nan=False)
    except (TypeError, ValueError) as error:
        raise ReconError(f"{path}: cannot write as JSON: {error}") from error
    atomic_write_text(path, text + "\n")


def append_json_line(path: str | os.PathLike, record: Any, allow_nan: bool = False) -> None:
    """Append one JSON record as a line, flushed to disk (a log: earlier lines are never rewritten).

    The record is encoded before the file is opened, so a record that is not valid JSON leaves
    the file untouched (ReconError naming the path). allow_nan: write NaN/Infinity as Python's
    json does (for logs read back by Python only).
    """
    try:
        line = json.dumps(record, allow_nan=allow_nan) + "\n"
    except (TypeError, ValueError) as error:
        raise ReconError(f"{path}: cannot write as JSON: {error}") from error
    target = Path(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        with open(target, "a", encoding="utf-8") as handle:
            handle.write(line)
            handle.flush()
            os.fsync(handle.fileno())
    except OSError as error:
        raise WriteError(f"cannot write {describe_os_error(error, target)}") from error


# mkstemp's names: '.' + the target's stem + '.' + 8 random characters + '.tmp' + the suffix.
_TEMPORARY_NAME = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.tmp(\.[^.]+)?$")


def remove_stale_temporaries(folder: str | os.PathLike) -> list[Path]:
    """Delete the temporary files atomic_path leaves when its process is killed mid-write.

    Only names of atomic_path's own pattern are touched, and only under `folder`, which must be
    a folder recon created (a run folder being resumed). Returns the deleted paths.
    """
    removed = []
    for path in Path(folder).rglob(".*.tmp*"):
        if path.is_file() and not path.is_symlink() and _TEMPORARY_NAME.match(path.name):
            path.unlink()
            removed.append(path)
    return removed
