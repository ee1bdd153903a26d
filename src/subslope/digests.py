"""Digests of the package's own source files, for keys that must change when the code
that made a cached result changes (the shard cache, the compile cache)."""

from __future__ import annotations

import hashlib
from functools import lru_cache
from pathlib import Path

__all__ = ["package_digest"]

_ROOT = Path(__file__).resolve().parent


@lru_cache(maxsize=8)
def package_digest(parts: tuple[str, ...]) -> str:
    """SHA-256 (hex) over the files of ``parts``: package-relative folders or files, each
    file's relative path and bytes, in sorted order (compiled ``__pycache__`` files left
    out). Cached per process: the sources do not change under a running job."""
    files: list[Path] = []
    for part in parts:
        path = _ROOT / part
        files += sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    digest = hashlib.sha256()
    for path in sorted(files):
        if "__pycache__" in path.parts or path.suffix == ".pyc":
            continue
        digest.update(path.relative_to(_ROOT).as_posix().encode())
        digest.update(b"\0")
        digest.update(path.read_bytes())
    return digest.hexdigest()
