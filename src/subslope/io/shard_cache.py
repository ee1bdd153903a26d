"""A folder of finished shards (and other results) keyed by what determines them.

Campaigns that differ in a few simulator choices (the systematics variants) share most
of what they simulate only where a choice does not reach: a shard of a scene that a
variant leaves alone has the same images in every variant. The cache holds each such
shard once, as ``<folder>/<scene>/<key>.h5``; the key (computed by
:func:`subslope.stages.simulate.shard_cache_key`) is the SHA-256 of everything the images
depend on, so a key that is present is the shard the job would write.

A cached shard is used only when it is the shard of its key: its identity (scene, shard
index, multiplier, config hash and seed, :func:`shard_identity`), recorded beside it as
``<key>.json`` when it entered the cache, matches both the shard's own attributes and
the request, and :func:`subslope.io.shards.verify_shard` has read every chunk against
its checksum; anything else is removed and the shard simulated again. A file enters and
leaves the cache as a copy of its own (a reflink, sharing the blocks, on file systems
that offer one: btrfs, XFS), never as a second name of a file a user may write through
(``cp other.h5 results/.../shard_0.h5`` writes into the inode a hard link would share)
or that Snakemake touches after a job. Both go through a temporary name beside the
target, and the identity record is written last, so an interrupted entry is never
taken. :func:`subslope.plan.cache_folder_problems` refuses a cache folder that overlaps
``results/``.

Results other than shards (the HST lens-light fits) are kept the same way, as a folder
``<folder>/_<kind>/<key>/`` of files and a ``manifest.json`` of their SHA-256 written
last: an entry without its manifest, or whose files do not match it, is removed and the
result computed again. Scene names start with a letter, so ``_<kind>`` never meets a
scene's folder.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from collections.abc import Mapping
from pathlib import Path

from subslope.digests import package_digest
from subslope.io.atomic import atomic_write, temporary_path, write_text
from subslope.io.shards import ShardError, file_sha256, verify_shard

__all__ = [
    "CODE_PARTS",
    "MANIFEST",
    "identity_path",
    "shard_identity",
    "code_digest",
    "cached_path",
    "cached_entry",
    "take_from_cache",
    "put_in_cache",
    "take_files_from_cache",
    "put_files_in_cache",
    "link_or_copy",
    "clone_or_copy",
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
    "config",
    "devices.py",
    "ragged.py",
    "_version.py",
)


#: The file that lists the files of a non-shard entry and their SHA-256.
MANIFEST = "manifest.json"


def code_digest(parts: tuple[str, ...] = CODE_PARTS) -> str:
    """SHA-256 over the files of ``parts`` (:func:`subslope.digests.package_digest`): with
    :data:`CODE_PARTS`, a change to the code that makes shards invalidates every cached
    shard, while one to the estimator, the statistics, the figures or the stages does
    not."""
    return package_digest(parts)


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


#: Linux ioctl FICLONE: make a file share another's blocks (copy on write).
_FICLONE = 0x40049409


def clone_or_copy(source: str | os.PathLike[str], target: str | os.PathLike[str]) -> Path:
    """Put a file of its own with the bytes of ``source`` at ``target`` (replacing it):
    a reflink where the file system offers one, else a copy; atomic at ``target``."""
    target = Path(target)
    with atomic_write(target) as tmp, open(source, "rb") as src, open(tmp, "wb") as dst:
        try:
            import fcntl

            fcntl.ioctl(dst.fileno(), _FICLONE, src.fileno())
        except (ImportError, OSError):
            shutil.copyfileobj(src, dst, 1 << 20)
    return target


def identity_path(folder: str | os.PathLike[str], scene: str, key: str) -> Path:
    """The identity record of the cached shard of ``key`` (``<key>.json`` beside it)."""
    return Path(folder) / scene / f"{key}.json"


#: The shard attributes that say which shard a file is.
IDENTITY_ATTRS = ("scene", "shard_index", "multiplier", "config_hash", "seed_spawn_key")


def shard_identity(path: str | os.PathLike[str]) -> dict:
    """Which shard the file at ``path`` is: its :data:`IDENTITY_ATTRS`, as JSON values."""
    from subslope.io.shards import open_shard

    with open_shard(path) as shard:
        attrs = shard.attrs
        ident = {k: attrs.get(k) for k in IDENTITY_ATTRS}
    return json.loads(
        json.dumps(ident, default=lambda v: v.tolist() if hasattr(v, "tolist") else str(v))
    )


def _identity_problem(path: Path, record: Path, request: Mapping) -> str | None:
    """Why the cached shard ``path`` is not the one ``request`` asks for, or None."""
    if not record.is_file():
        return f"{path} has no identity record {record.name}"
    try:
        recorded = json.loads(record.read_text(encoding="utf-8"))
        stored = shard_identity(path)
    except (OSError, ValueError, ShardError) as exc:
        return f"{path}: {exc}"
    if stored != recorded:
        return f"{path} is not the shard its identity record names ({stored} != {recorded})"
    for name, want in request.items():
        have = stored.get(name)
        if want is not None and (have is None or float(have) != float(want)):
            return f"{path} holds {name} = {have}, the key asks for {want}"
    return None


def take_from_cache(
    folder: str | os.PathLike[str],
    scene: str,
    key: str,
    out_path: str | os.PathLike[str],
    *,
    shard: int | None = None,
    multiplier: float | None = None,
) -> bool:
    """Put the cached shard of ``key`` at ``out_path`` and return True, or return False
    when the cache has none, or had one that is corrupt or not the shard of the key
    (scene, ``shard`` index and ``multiplier`` against its attributes and its identity
    record), which is then removed."""
    path = cached_path(folder, scene, key)
    record = identity_path(folder, scene, key)
    if not path.exists():
        return False
    try:
        verify_shard(path)
        problem = _identity_problem(path, record, {"shard_index": shard, "multiplier": multiplier})
        if problem is None and shard_identity(path).get("scene") != scene:
            problem = f"{path} is a shard of another scene"
    except ShardError as exc:
        problem = str(exc)
    if problem is not None:
        log.warning("removing a cached shard that cannot be used: %s", problem)
        path.unlink(missing_ok=True)
        record.unlink(missing_ok=True)
        return False
    clone_or_copy(path, out_path)
    log.info("shard taken from the cache %s", path)
    return True


def put_in_cache(
    folder: str | os.PathLike[str], scene: str, key: str, shard_path: str | os.PathLike[str]
) -> Path:
    """Enter a copy of the finished shard at ``shard_path`` into the cache under ``key``,
    then its identity record."""
    path = clone_or_copy(shard_path, cached_path(folder, scene, key))
    write_text(identity_path(folder, scene, key), json.dumps(shard_identity(path), indent=1) + "\n")
    log.info("shard put in the cache %s", path)
    return path


def cached_entry(folder: str | os.PathLike[str], kind: str, key: str) -> Path:
    """The folder of the ``kind`` entry of ``key`` in the cache ``folder``."""
    return Path(folder) / f"_{kind}" / key


def take_files_from_cache(
    folder: str | os.PathLike[str],
    kind: str,
    key: str,
    outputs: Mapping[str, str | os.PathLike[str]],
) -> bool:
    """Put the cached files of ``key`` at ``outputs`` (file name in the entry → target)
    and return True; False when the cache has no complete entry (an entry whose files do
    not match its manifest is removed)."""
    entry = cached_entry(folder, kind, key)
    manifest = entry / MANIFEST
    if not manifest.is_file():
        return False
    try:
        listed = json.loads(manifest.read_text())
        good = set(listed) == set(outputs) and all(
            file_sha256(entry / name) == listed[name] for name in outputs
        )
    except (OSError, ValueError):
        good = False
    if not good:
        log.warning("removing a %s cache entry that does not match its manifest: %s", kind, entry)
        shutil.rmtree(entry, ignore_errors=True)
        return False
    for name, target in outputs.items():
        clone_or_copy(entry / name, target)
    log.info("%s taken from the cache %s", kind, entry)
    return True


def put_files_in_cache(
    folder: str | os.PathLike[str],
    kind: str,
    key: str,
    outputs: Mapping[str, str | os.PathLike[str]],
) -> Path:
    """Enter the finished files ``outputs`` (file name in the entry → file) under ``key``;
    the manifest is written last, so an interrupted entry is never taken."""
    entry = cached_entry(folder, kind, key)
    for name, source in outputs.items():
        clone_or_copy(source, entry / name)
    listed = {name: file_sha256(entry / name) for name in outputs}
    write_text(entry / MANIFEST, json.dumps(listed, indent=1, sort_keys=True) + "\n")
    log.info("%s put in the cache %s", kind, entry)
    return entry
