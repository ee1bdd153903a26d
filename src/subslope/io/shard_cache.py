"""A folder of finished shards keyed by what determines their images.

Campaigns that differ in a few simulator choices (the systematics variants) share most
of what they simulate only where a choice does not reach: a shard of a scene that a
variant leaves alone has the same images in every variant. The cache holds each such
shard once, as ``<folder>/<scene>/<key>.h5``; the key (computed by
:func:`subslope.stages.simulate.shard_cache_key`) is the SHA-256 of everything the images
depend on, so a key that is present is the shard the job would write.

A cached file is used only after :func:`subslope.io.shards.verify_shard` has read every
chunk against its checksum; a bad one is removed and the shard simulated again. Files
enter the cache and leave it as hard links where the two folders share a file system
(no second copy on disk; the shard writers never write into an existing file, so a link
cannot be changed through the other name), else as copies, always through a temporary
name beside the target.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
from functools import lru_cache
from pathlib import Path

from subslope.io.atomic import temporary_path
from subslope.io.shards import ShardError, verify_shard

__all__ = [
    "CODE_PARTS",
    "code_digest",
    "cached_path",
    "take_from_cache",
    "put_in_cache",
    "link_or_copy",
]

log = logging.getLogger(__name__)

#: The parts of the package that draw, render and write a shard (and nothing that only
#: reads one): their files enter every key.
CODE_PARTS = (
    "physics",
    "render",
    "simulation",
    "io",
    "schemas",
    "data",
    "config.py",
    "devices.py",
    "ragged.py",
    "_version.py",
)


@lru_cache(maxsize=1)
def code_digest() -> str:
    """SHA-256 over the files of :data:`CODE_PARTS` (relative path and bytes, sorted):
    a change to the code that makes shards invalidates every cached shard, while one to
    the estimator, the statistics, the figures or the stages does not."""
    root = Path(__file__).resolve().parents[1]
    files: list[Path] = []
    for part in CODE_PARTS:
        path = root / part
        files += sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    digest = hashlib.sha256()
    for path in sorted(files):
        if "__pycache__" in path.parts or path.suffix == ".pyc":
            continue
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(b"\0")
        digest.update(path.read_bytes())
    return digest.hexdigest()


def cached_path(folder: str | os.PathLike[str], scene: str, key: str) -> Path:
    """Where the shard of ``key`` lives in the cache ``folder``."""
    return Path(folder) / scene / f"{key}.h5"


def link_or_copy(source: str | os.PathLike[str], target: str | os.PathLike[str]) -> Path:
    """Put ``source`` at ``target`` (replacing it) as a hard link, or a copy where a link
    is impossible (another file system, no link support); atomic at ``target``."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_path(target)
    tmp.unlink()  # os.link needs a free name; the random name stays unique
    try:
        try:
            os.link(source, tmp)
        except OSError:
            shutil.copyfile(source, tmp)
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)
    return target


def take_from_cache(
    folder: str | os.PathLike[str], scene: str, key: str, out_path: str | os.PathLike[str]
) -> bool:
    """Put the cached shard of ``key`` at ``out_path`` and return True, or return False
    when the cache has none (or had a corrupt one, which is then removed)."""
    path = cached_path(folder, scene, key)
    if not path.exists():
        return False
    try:
        verify_shard(path)
    except ShardError as exc:
        log.warning("removing a corrupt cached shard: %s", exc)
        path.unlink(missing_ok=True)
        return False
    link_or_copy(path, out_path)
    log.info("shard taken from the cache %s", path)
    return True


def put_in_cache(
    folder: str | os.PathLike[str], scene: str, key: str, shard_path: str | os.PathLike[str]
) -> Path:
    """Enter the finished shard at ``shard_path`` into the cache under ``key``."""
    path = link_or_copy(shard_path, cached_path(folder, scene, key))
    log.info("shard put in the cache %s", path)
    return path
