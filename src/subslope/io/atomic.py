"""Atomic file writes: a result file is either complete or absent, never partial.

Every writer of the package goes through :func:`atomic_write`: the content goes to a
temporary file in the destination folder (same file system, so the final
``os.replace`` is atomic), which replaces the destination only once it is complete; on
any error the temporary file is removed and the previous version of the destination,
if any, is left as it was. A writer killed before it can clean up (SIGKILL) leaves its
temporary behind; the next write of the same file removes it. The final file gets the
permissions of a normally created file (``0o666`` less the process umask), not the
``0o600`` of a temporary file. A write that runs out of disk space raises
:class:`DiskFullError`, naming the file, its file system and the space left there, and
leaves neither a partial file nor a temporary behind.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import os
import shutil
import socket
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

__all__ = [
    "remove_stale_temporaries_under",
    "DiskFullError",
    "ResultFileError",
    "read_json",
    "atomic_write",
    "remove_stale_temporaries",
    "temporary_path",
    "write_text",
    "write_csv",
    "write_json",
]


class DiskFullError(OSError):
    """A result could not be written: its file system is full."""


class ResultFileError(ValueError):
    """A result file cannot be read: truncated, corrupt or changed after it was written."""


def read_json(path: str | os.PathLike[str]) -> Any:
    """The content of a JSON result file written by :func:`write_json`; a file that is
    not valid JSON raises :class:`ResultFileError` naming it and how to recover."""
    import json

    path = Path(path)
    text = path.read_text(encoding="utf-8")
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ResultFileError(
            f"{path} is not valid JSON ({exc}): it was cut short or changed after it was "
            "written; delete it and run snakemake again to write it anew"
        ) from None


def _mount_point(path: Path) -> Path:
    path = path.resolve()
    while not os.path.ismount(path) and path != path.parent:
        path = path.parent
    return path


def _disk_full(exc: BaseException, folder: Path) -> bool:
    """Whether ``exc`` is a failed write for want of space: ``ENOSPC`` (HDF5 has it in
    its message only), or torch's
    "unexpected pos" (its zip writer's report of a short write) on a nearly full disk."""
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    if "No space left on device" in str(exc):  # HDF5 reports it in its message only
        return True
    if isinstance(exc, RuntimeError) and "unexpected pos" in str(exc):
        try:
            return shutil.disk_usage(folder).free < 64 * 2**20
        except OSError:
            return False
    return False


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _host() -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in socket.gethostname())


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def remove_stale_temporaries(path: str | os.PathLike[str]) -> list[Path]:
    """Remove the temporaries of ``path`` left by killed writers on this host: the files
    ``.<name>.<host>.<pid>.*.tmp`` whose process no longer runs. Temporaries of live
    processes and of other hosts are kept. Returns the paths removed."""
    path = Path(path)
    removed = []
    prefix = f".{path.name}.{_host()}."
    for tmp in path.parent.glob(f".{glob.escape(path.name)}.*.tmp"):
        rest = tmp.name[len(prefix) :] if tmp.name.startswith(prefix) else ""
        pid = rest.split(".", 1)[0]
        if pid.isdigit() and not _alive(int(pid)):
            tmp.unlink(missing_ok=True)
            removed.append(tmp)
    return removed


def remove_stale_temporaries_under(folder: str | os.PathLike[str]) -> list[Path]:
    """:func:`remove_stale_temporaries` for every temporary anywhere under ``folder``
    (the workflow calls it on ``results/`` when it starts: a shard-sized leftover of a
    killed job goes at the next run, not when that shard is written again)."""
    removed = []
    root = Path(folder)
    for tmp in root.rglob(".*.tmp") if root.is_dir() else []:
        name = tmp.name[1:-4]  # <name>.<host>.<pid>.<random>
        parts = name.rsplit(".", 3)
        if len(parts) == 4:
            removed += remove_stale_temporaries(tmp.with_name(parts[0]))
    return removed


def temporary_path(path: str | os.PathLike[str]) -> Path:
    """A new, empty temporary file beside ``path`` (its folder is created), named
    ``.<name>.<host>.<pid>.<random>.tmp``; stale ones of killed writers are removed
    first (:func:`remove_stale_temporaries`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.{_host()}.{os.getpid()}.", suffix=".tmp", dir=path.parent
    )
    os.close(fd)
    return Path(tmp)


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Context manager yielding a temporary path to write; on success it replaces ``path``.

    ::

        with atomic_write("results/x.h5") as tmp:
            with h5py.File(tmp, "w") as fh:
                ...
    """
    path = Path(path)
    tmp = temporary_path(path)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except (OSError, RuntimeError) as exc:
        if not _disk_full(exc, path.parent):
            raise
        tmp.unlink(missing_ok=True)
        free = shutil.disk_usage(path.parent).free
        raise DiskFullError(
            errno.ENOSPC,
            f"no space left to write {path}: the file system mounted at "
            f"{_mount_point(path.parent)} has {free / 2**20:.1f} MiB free; free space "
            f"there and run again (nothing was written: {path} is as it was)",
        ) from exc
    finally:
        tmp.unlink(missing_ok=True)


def write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns the path."""
    path = Path(path)
    with atomic_write(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path


def write_json(path: str | os.PathLike[str], obj: Any, *, indent: int = 2) -> Path:
    """Write ``obj`` as JSON (with a final newline) to ``path`` atomically."""
    import json

    return write_text(path, json.dumps(obj, indent=indent) + "\n")


def write_csv(
    path: str | os.PathLike[str],
    rows: Sequence[Mapping[str, Any]],
    columns: Sequence[str] | None = None,
) -> Path:
    """Write ``rows`` (one mapping per row) as CSV to ``path`` atomically."""
    import pandas as pd

    frame = pd.DataFrame(list(rows), columns=None if columns is None else list(columns))
    return write_text(path, frame.to_csv(index=False))
