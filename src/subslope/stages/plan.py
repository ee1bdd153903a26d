"""Planning of the workflow: which shard jobs a config asks for, their paths, and the
seeds derived for the later stages. Pure Python and numpy (no torch, h5py or plotting),
so ``snakemake -n`` stays fast.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from typing import Any

import numpy as np

from subslope import config as _config
from subslope.simulation.resolve import resolved_scene, scene_multipliers

__all__ = [
    "SHARD_DIR",
    "RUN_ONLY_RENDER_KEYS",
    "derived_seed",
    "multiplier_label",
    "shard_job_config",
    "shard_jobs",
    "shard_path",
]

#: Folder of the simulated shards (rule simulate_shard).
SHARD_DIR = "results/simulate_shard"


def multiplier_label(a: float) -> str:
    """Path label of a concentration multiplier (``1.0`` → ``'1'``, ``0.5`` → ``'0.5'``)."""
    return f"{float(a):g}"


def shard_path(
    scene: str, shard: int, multiplier: float | None = None, root: str = SHARD_DIR
) -> str:
    """``<root>/<scene>/shard_<k>.h5`` or ``<root>/<scene>/a<a>/shard_<k>.h5``."""
    if multiplier is None:
        return f"{root}/{scene}/shard_{int(shard)}.h5"
    return f"{root}/{scene}/a{multiplier_label(multiplier)}/shard_{int(shard)}.h5"


def shard_jobs(config: Mapping[str, Any]) -> list[dict[str, Any]]:
    """One entry ``{scene, shard, multiplier, path}`` per shard the config asks for."""
    config = _config.validate(config)
    jobs = []
    for name, counts in config["simulation"]["scenes"].items():
        scene, _ = resolved_scene(config, name)
        n_img = int(counts["images_per_shard"])
        if n_img % scene.images_per_set:
            raise _config.ConfigError(
                f"config key simulation.scenes.{name}.images_per_shard = {n_img} must be a "
                "multiple "
                f"of scenes.{name}.images_per_set = {scene.images_per_set}"
            )
        mults = scene_multipliers(config, scene)
        for k in range(int(counts["n_shards"])):
            for a in mults or (None,):
                jobs.append(
                    {"scene": name, "shard": k, "multiplier": a, "path": shard_path(name, k, a)}
                )
    return jobs


def derived_seed(seed: int, name: str) -> int:
    """A 32-bit seed for the stream ``name``, derived from the global ``seed``."""
    key = int.from_bytes(hashlib.sha256(name.encode()).digest()[:4], "little")
    return int(np.random.SeedSequence([int(seed), key]).generate_state(1)[0])


#: ``simulation.render`` keys that change how a shard job runs, not its images: they
#: reach the job from the workflow's config, not through its (rerun-triggering) params.
RUN_ONLY_RENDER_KEYS = ("batch_size", "device")


def shard_job_config(
    config: Mapping[str, Any], scene: str, multiplier: float | str | None = None
) -> dict[str, Any]:
    """The resolved configuration one shard job of ``scene`` needs, and nothing else.

    The validated sections that determine its images: ``seed``, ``instrument``,
    ``cosmology``, the scene's spec, its ``simulation.scenes`` entry, ``simulation.sources``
    and the render settings without :data:`RUN_ONLY_RENDER_KEYS`; for a CDM scene the
    multipliers up to and including ``multiplier`` (its position in the list sets the
    shard's seed, so appending a multiplier changes no existing job; null for the other
    scenes). Every stage is off,
    so the job's own validation checks only what the job uses. Passed to the job as a
    Snakemake param, so a change of any of these values reruns exactly the shards it
    affects.
    """
    config = _config.validate(config)
    sim = config["simulation"]
    sc, _ = resolved_scene(config, scene)
    mults = scene_multipliers(config, sc)
    kept: list[float] | None = None
    if mults is not None and multiplier is not None:
        a = float(multiplier)
        index = next(k for k, m in enumerate(mults) if abs(m - a) <= 1e-12 * max(abs(a), 1.0))
        kept = list(mults[: index + 1])
    return {
        "seed": config["seed"],
        "instrument": config["instrument"],
        "cosmology": config["cosmology"],
        "scenes": {scene: (config.get("scenes") or {}).get(scene) or {}},
        "simulation": {
            "scenes": {scene: sim["scenes"][scene]},
            "multipliers": kept,
            "render": {k: v for k, v in sim["render"].items() if k not in RUN_ONLY_RENDER_KEYS},
            "sources": sim["sources"],
        },
        "stages": {name: False for name in _config.STAGE_NEEDS},
    }
