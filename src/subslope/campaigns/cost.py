"""What a campaign costs before it runs (``subslope cost``): images and shards, CPU-hours
of simulation, disk of the shards, GPU-hours of training, from per-image costs measured
on a finished campaign (its ``results/``) or, until measured, the stated defaults below.

The defaults are measurements of record, not guesses: the simulation cost and the shard
size per image are those of the reduced campaign's training shards on the 2-core
development machine (notebook entry "End to end: a training shard per image": 43.9 ms a
shard image on an Intel Xeon with AVX-512, about twice that on an AVX2-only AMD EPYC;
about 42 KB a training image at N_sub = 1500 + line of sight: its pixels ~24 KB, its
subhalos ~16 KB, docs/simulation.md). Training throughput on a GPU has not been
measured here (``benchmarks/gpu_check.sh``); its default is the reference analysis's
statement (about 20 epochs of 5·10⁶ images in about 100 GPU-hours on V100s, i.e. about
280 images a second), to be replaced by the number the GPU check measures.

That cost per image holds for the training scene; an image of another scene costs it
times :func:`scene_cost_factor`, the ratio of the renderer's measured cost at the
scene's mean N_sub and subhalo profile to its cost at the training scene's
(:data:`RENDER_SECONDS`): the reference CDM sets, with up to 12,000 NFW or tNFW
subhalos an image, cost several training images each.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

__all__ = [
    "RENDER_SECONDS",
    "render_seconds",
    "scene_cost_factor",
    "DEFAULT_BYTES_PER_IMAGE",
    "DEFAULT_GPU_IMAGES_PER_S",
    "DEFAULT_SECONDS_PER_IMAGE",
    "CampaignCost",
    "campaign_cost",
    "measured_costs",
]

#: Seconds of one CPU core per simulated shard image (see the module docstring).
DEFAULT_SECONDS_PER_IMAGE = 0.0439
#: Bytes of a shard per image.
DEFAULT_BYTES_PER_IMAGE = 42_000
#: Training images per second of one GPU (the reference analysis's V100 figure).
DEFAULT_GPU_IMAGES_PER_S = 5e6 * 20 / (100 * 3600)

#: Render cost of one image on one core against its number of subhalos, per subhalo
#: profile, line-of-sight halos on: ``(N_sub, seconds)`` points of the default renderer
#: (``benchmarks/simulate_vs_lenstronomy.py``, one thread, the 2-core Intel Xeon of the
#: development machine; notebook entry "Large subhalo populations"), joined by straight
#: lines and continued along the last one. Only the ratios between scenes are used.
RENDER_SECONDS: dict[str, tuple[tuple[int, float], ...]] = {
    "epl": ((0, 0.0094), (1500, 0.0372), (3000, 0.0640), (6000, 0.1315), (12000, 0.2799)),
    "nfw": ((0, 0.0094), (1500, 0.0475), (3000, 0.0843), (6000, 0.1699), (12000, 0.3698)),
    "tnfw": ((0, 0.0094), (1500, 0.0779), (3000, 0.1487), (6000, 0.3004), (12000, 0.6345)),
}


def render_seconds(profile: str, n_sub: float) -> float:
    """Seconds of one core to render an image of ``n_sub`` subhalos of ``profile``
    (:data:`RENDER_SECONDS`, linear between its points and beyond the last)."""
    if profile not in RENDER_SECONDS:
        known = sorted(RENDER_SECONDS)
        raise ValueError(f"no render cost for subhalo profile {profile!r}; known: {known}")
    pts = RENDER_SECONDS[profile]
    n = max(0.0, float(n_sub))
    # the segment holding n, or the last one continued beyond the last point
    k = next((i for i in range(1, len(pts)) if n <= pts[i][0]), len(pts) - 1)
    (n0, s0), (n1, s1) = pts[k - 1], pts[k]
    return s0 + (s1 - s0) * (n - n0) / (n1 - n0)


def _scene_seconds(scene) -> float:
    """Expected :func:`render_seconds` of an image of a
    :class:`subslope.simulation.scenes.Scene`: averaged over a uniform N_sub prior, at
    the prior's mean otherwise."""
    if not scene.components.subhalos:
        return render_seconds("epl", 0)
    profile, count = scene.subhalos.profile, scene.subhalos.count
    if count.dist == "uniform_int":
        grid = [count.low + (count.high - count.low) * k / 200 for k in range(201)]
        return sum(render_seconds(profile, n) for n in grid) / len(grid)
    return render_seconds(profile, count.mean)


def scene_cost_factor(config: Mapping[str, Any], name: str) -> float:
    """Cost of an image of scene ``name`` relative to an image of the training scene:
    :func:`render_seconds` at each scene's subhalo profile, averaged over its N_sub
    prior (a scene without subhalos at N_sub = 0)."""
    from subslope import config as _config
    from subslope.plan import resolved_scene

    scene, _ = resolved_scene(config, name)
    train, _ = resolved_scene(config, _config.STREAMED_SCENE)
    return _scene_seconds(scene) / _scene_seconds(train)


@dataclass
class CampaignCost:
    """The cost of one campaign (units in the field names)."""

    shard_jobs: int
    images: int
    cpu_hours_by_scene: dict[str, float]
    training_images: int
    max_epochs: int
    cpu_hours_simulation: float
    disk_gb_shards: float
    gpu_hours_training: float
    seconds_per_image: float
    bytes_per_image: float
    gpu_images_per_s: float
    sources: dict[str, str]

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def campaign_cost(
    config: Mapping[str, Any],
    *,
    seconds_per_image: float = DEFAULT_SECONDS_PER_IMAGE,
    bytes_per_image: float = DEFAULT_BYTES_PER_IMAGE,
    gpu_images_per_s: float = DEFAULT_GPU_IMAGES_PER_S,
    sources: Mapping[str, str] | None = None,
) -> CampaignCost:
    """The cost of ``config``'s campaign: every shard image simulated once
    (``seconds_per_image`` of one core for a training image, times
    :func:`scene_cost_factor` for an image of another scene), stored at
    ``bytes_per_image``, and the
    training images seen ``training.max_epochs`` times at ``gpu_images_per_s`` (an upper
    bound where early stopping ends training sooner)."""
    from subslope import config as _config
    from subslope.plan import shard_jobs

    config = _config.validate(config)
    jobs = shard_jobs(config)
    per_shard = {n: int(c["images_per_shard"]) for n, c in config["simulation"]["scenes"].items()}
    images = sum(per_shard[j["scene"]] for j in jobs)
    factors = {name: scene_cost_factor(config, name) for name in {j["scene"] for j in jobs}}
    by_scene: dict[str, float] = {}
    for j in jobs:
        hours = per_shard[j["scene"]] * seconds_per_image * factors[j["scene"]] / 3600
        by_scene[j["scene"]] = by_scene.get(j["scene"], 0.0) + hours
    train = config["simulation"]["scenes"].get(_config.STREAMED_SCENE, {})
    training_images = int(train.get("n_shards", 0)) * int(train.get("images_per_shard", 0))
    epochs = int(config["training"]["max_epochs"])
    return CampaignCost(
        shard_jobs=len(jobs),
        images=images,
        cpu_hours_by_scene=dict(sorted(by_scene.items(), key=lambda kv: -kv[1])),
        training_images=training_images,
        max_epochs=epochs,
        cpu_hours_simulation=sum(by_scene.values()),
        disk_gb_shards=images * bytes_per_image / 1e9,
        gpu_hours_training=training_images * epochs / gpu_images_per_s / 3600,
        seconds_per_image=seconds_per_image,
        bytes_per_image=bytes_per_image,
        gpu_images_per_s=gpu_images_per_s,
        sources=dict(sources or {}),
    )


def measured_costs(results: str | os.PathLike[str]) -> dict[str, float]:
    """Seconds per image and bytes per image of the training shards of a finished
    campaign: its shard files and their Snakemake benchmark files (``s``). Keys absent
    where the campaign has no training shard or benchmark."""
    import csv

    from subslope.io.shards import open_shard

    root = Path(results)
    shards = sorted((root / "simulate_shard" / "train").glob("shard_*.h5"))
    images = seconds = size = 0.0
    timed = 0.0
    for shard in shards:
        with open_shard(shard) as opened:
            n = len(opened)
        images += n
        size += shard.stat().st_size
        bench = root / "benchmarks" / "simulate_shard" / "train" / f"{shard.stem}.tsv"
        if bench.is_file():
            with bench.open(encoding="utf-8") as fh:
                rows = list(csv.DictReader(fh, delimiter="\t"))
            if rows and math.isfinite(float(rows[-1]["s"])):
                seconds += float(rows[-1]["s"])
                timed += n
    out: dict[str, float] = {}
    if images:
        out["bytes_per_image"] = size / images
    if timed:
        out["seconds_per_image"] = seconds / timed
    return out
