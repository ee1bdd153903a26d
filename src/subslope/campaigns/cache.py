"""The cache of finished results (``simulation.shard_cache``, :mod:`subslope.io.shard_cache`):
what it holds, what uses it, and pruning (``subslope cache du``, ``subslope cache prune``).

An entry is *referenced* when a config in use would take it: its key is one that a
shard job (or the lens-light fit) of that config, or of one of its systematics variants,
computes with the code of this checkout. It is *held* when another name on the file
system links its file: it is the ``results/`` shard or fit of the campaign that made it
(entries are hard links of those; a copy across file systems holds nothing). Pruning
removes what is neither referenced nor held, and what is held only with ``force``:
removing a held entry frees no disk space while the results that link it exist.
"""

from __future__ import annotations

import os
import shutil
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from subslope import config as _config
from subslope.io.shard_cache import MANIFEST
from subslope.plan import cache_folder_problems, shard_job_config, shard_jobs
from subslope.stages.domain import lens_light_fit_key
from subslope.stages.simulate import shard_cache_key

__all__ = [
    "CacheEntry",
    "Campaign",
    "cache_entries",
    "campaigns_in_use",
    "referenced_keys",
    "cache_usage",
    "prune_cache",
    "format_size",
]


@dataclass
class CacheEntry:
    """One cache entry: a shard file (``kind`` ``shard``, ``group`` its scene) or a
    folder of files (``kind`` e.g. ``lens_light``, ``group`` the kind)."""

    kind: str
    group: str
    key: str
    path: Path
    #: bytes of its files
    size: int
    #: True when another name links one of its files (a results/ file)
    held: bool
    #: run names of the configs in use that reference it
    used_by: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class Campaign:
    """A config in use: its ``run_name`` and validated config."""

    name: str
    config: dict[str, Any]


def _files(path: Path) -> list[Path]:
    return [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())


def cache_entries(folder: str | os.PathLike[str]) -> list[CacheEntry]:
    """Every entry of the cache ``folder`` (none when it does not exist)."""
    root = Path(folder)
    entries: list[CacheEntry] = []
    if not root.is_dir():
        return entries
    for sub in sorted(p for p in root.iterdir() if p.is_dir()):
        if sub.name.startswith("_"):
            kind = sub.name[1:]
            items = sorted(p for p in sub.iterdir() if p.is_dir())
        else:  # a shard is an entry only with its identity record: nothing else is removed
            kind = "shard"
            items = sorted(p for p in sub.glob("*.h5") if p.with_suffix(".json").is_file())
        for item in items:
            stats = [p.stat() for p in _files(item) if p.name != MANIFEST]
            entries.append(
                CacheEntry(
                    kind=kind,
                    group=sub.name if kind == "shard" else kind,
                    key=item.stem if kind == "shard" else item.name,
                    path=item,
                    size=sum(s.st_size for s in stats),
                    held=any(s.st_nlink > 1 for s in stats),
                )
            )
    return entries


def campaigns_in_use(
    files: Sequence[str | os.PathLike[str]], *, root: str | os.PathLike[str] = "."
) -> list[Campaign]:
    """The campaigns of the config ``files`` (each read with its layers, as
    ``--configfile``) and of their systematics variants, validated."""
    from subslope.campaigns.systematics import read_variants

    campaigns = []
    for file in files:
        raw = _config.read_files([file])
        config = _config.apply_env_overrides(_config.validate(raw))
        campaigns.append(Campaign(config["run_name"], config))
        campaigns += [
            Campaign(v.name, _config.validate(v.config)) for v in read_variants(raw, root=root)
        ]
    return campaigns


def referenced_keys(campaigns: Iterable[Campaign]) -> dict[tuple[str, str], set[str]]:
    """``{(cache folder, key): {run names}}`` of every entry the ``campaigns`` would take:
    each shard job's key and, where the HST cutouts are present, the lens-light fit's."""
    used: dict[tuple[str, str], set[str]] = defaultdict(set)
    for campaign in campaigns:
        config = campaign.config
        folder = config["simulation"].get("shard_cache")
        if not folder:
            continue
        folder = os.path.abspath(folder)
        jobs: dict[tuple[str, Any], dict[str, Any]] = {}
        for job in shard_jobs(config):
            scene, shard, a = job["scene"], job["shard"], job["multiplier"]
            if (scene, a) not in jobs:
                jobs[scene, a] = shard_job_config(config, scene, a)
            used[folder, shard_cache_key(jobs[scene, a], scene, shard, a)].add(campaign.name)
        hst = Path(config["data"]["resources_dir"]) / "hst"
        if hst.is_dir():
            try:
                used[folder, lens_light_fit_key(config, hst)].add(campaign.name)
            except FileNotFoundError:
                pass  # the PSF is not fetched yet: no fit can have been made from it
    return used


def cache_usage(campaigns: Sequence[Campaign]) -> dict[Path, list[CacheEntry]]:
    """The entries of every cache folder the ``campaigns`` use, each with the run names
    that reference it (:func:`referenced_keys`)."""
    problems = [p for c in campaigns for p in cache_folder_problems(c.config)]
    if problems:
        raise _config.ConfigError("\n".join(problems))
    used = referenced_keys(campaigns)
    folders = sorted(
        {
            Path(os.path.abspath(c.config["simulation"]["shard_cache"]))
            for c in campaigns
            if c.config["simulation"].get("shard_cache")
        }
    )
    out: dict[Path, list[CacheEntry]] = {}
    for folder in folders:
        entries = cache_entries(folder)
        for entry in entries:
            entry.used_by = sorted(used.get((str(folder), entry.key), ()))
        out[folder] = entries
    return out


def prune_cache(
    usage: Mapping[Path, list[CacheEntry]], *, force: bool = False, dry_run: bool = False
) -> tuple[list[CacheEntry], list[CacheEntry]]:
    """Remove the unreferenced entries of ``usage`` (:func:`cache_usage`): those not held
    by a results/ link, and with ``force`` the held ones too. Returns (removed, kept
    because held); ``dry_run`` removes nothing."""
    removed, kept = [], []
    for entries in usage.values():
        for entry in entries:
            if entry.used_by:
                continue
            if entry.held and not force:
                kept.append(entry)
                continue
            if not dry_run:
                if entry.path.is_dir():
                    shutil.rmtree(entry.path)
                else:
                    entry.path.unlink(missing_ok=True)
                    entry.path.with_suffix(".json").unlink(missing_ok=True)
            removed.append(entry)
    return removed, kept


def format_size(n: float) -> str:
    """``n`` bytes as B, KB, MB, GB or TB (powers of 1000)."""
    for unit in ("B", "KB", "MB", "GB"):
        if abs(n) < 1000:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} TB"
