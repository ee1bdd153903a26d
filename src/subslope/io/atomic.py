"""Atomic file writes: a result file is either complete or absent, never partial.

Every writer of the package goes through :func:`atomic_write`: the content goes to a
temporary file in the destination folder (same file system, so the final
``os.replace`` is atomic), which replaces the destination only once it is complete; on
any error the temporary file is removed and the previous version of the destination,
if any, is left as it was. The final file gets the permissions of a normally created
file (``0o666`` less the process umask), not the ``0o600`` of a temporary file.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

__all__ = ["atomic_write", "temporary_path", "write_text", "write_csv", "write_json"]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def temporary_path(path: str | os.PathLike[str]) -> Path:
    """A new, empty temporary file beside ``path`` (its folder is created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
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
