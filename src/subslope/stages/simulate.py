"""Stage ``simulate``: image shards, the whitening statistics of the training shards and
the scene example figures (rules simulate_shard, simulate_cdm_shard, compute_whitening,
plot_scene_examples).

The renderer, the estimator's whitening and the figures are imported by the functions
that use them: a shard job that finds its shard in the cache never loads torch.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from subslope.config import config_hash
from subslope.io.shard_cache import code_digest, put_in_cache, take_from_cache
from subslope.io.shards import FORMAT_VERSION
from subslope.plan import runnable_config, with_stages_off
from subslope.simulation.resolve import simulation_sections

__all__ = [
    "simulate_shard",
    "simulate_shard_job",
    "runnable_config",
    "shard_cache_key",
    "compute_whitening",
    "attach_light_fit",
    "plot_scene_examples_from_shard",
]


def shard_cache_key(
    job: Mapping[str, Any], scene: str, shard: int, multiplier: float | None = None
) -> str:
    """Key of one shard in a shard cache (:mod:`subslope.io.shard_cache`): SHA-256 of
    what its images depend on: the resolved sections of ``job``
    (:func:`subslope.simulation.resolve.simulation_sections`; a job holds the multipliers
    up to its own, whose position sets its seed), the shard index, the multiplier, the
    shard format and the code that makes shards (:func:`subslope.io.shard_cache.code_digest`).
    ``n_shards`` is not part of it: shard k of a scene is the same file in a campaign of
    4 shards and in one of 8."""
    return config_hash(
        {
            "sections": simulation_sections(job, scene),
            "shard": int(shard),
            "multiplier": None if multiplier is None else float(multiplier),
            "format_version": FORMAT_VERSION,
            "code": code_digest(),
        }
    )


def simulate_shard(config: Mapping[str, Any], scene: str, shard: int, out_path, **kwargs) -> Path:
    """:func:`subslope.simulation.shard.simulate_shard`."""
    from subslope.simulation.shard import simulate_shard as simulate

    return simulate(config, scene, shard, out_path, **kwargs)


def compute_whitening(config: Mapping[str, Any], paths, out_path) -> dict:
    """:func:`subslope.nre.whitening.compute_whitening` of the training shards ``paths``
    after the config's input transform (:func:`subslope.stages.train.input_transform`)."""
    from subslope.nre.whitening import compute_whitening as whitening
    from subslope.stages.train import input_transform

    return whitening(paths, out_path, inputs=input_transform(config))


def attach_light_fit(config: Mapping[str, Any], src, dst) -> Path:
    """Copy the shard ``src`` to ``dst`` with the lens-light fit of every image added, as
    a shard job with ``simulation.light_fit`` on makes it (the config's detector and lens
    centre, the shard's PSF): for shards simulated without it."""
    import numpy as np

    from subslope.io.shards import open_shard, with_light_fit
    from subslope.simulation.observing import fit_input_light_of

    with open_shard(src) as shard:
        images = np.asarray(shard.images[:], dtype=np.float32)
        theta_e, psf = np.asarray(shard.params["theta_e"]), np.asarray(shard.psf)
    return with_light_fit(src, dst, fit_input_light_of(config, images, theta_e, psf))


def plot_scene_examples_from_shard(*args, **kwargs):
    """:func:`subslope.figures.gallery.plot_scene_examples_from_shard`."""
    from subslope.figures.gallery import plot_scene_examples_from_shard as plot

    return plot(*args, **kwargs)


def simulate_shard_job(
    job: Mapping[str, Any],
    run: Mapping[str, Any],
    scene: str,
    shard: int,
    out_path: str | os.PathLike[str],
    *,
    multiplier: float | None = None,
    threads: int | None = None,
) -> Path:
    """One shard job of the workflow: ``job`` is its resolved configuration
    (:func:`subslope.plan.shard_job_config`, the rule's params); ``run`` the
    workflow's config, from which only the values that must not rerun a finished shard
    are taken (:func:`runnable_config`; ``simulation.shard_cache``: a shard of the same
    key there is taken instead of simulated, and a new one is put there); ``threads``:
    torch's CPU threads while simulating."""
    job = with_stages_off(job)
    cache = run["simulation"].get("shard_cache")
    key = shard_cache_key(job, scene, shard, multiplier) if cache else ""
    if cache and take_from_cache(cache, scene, key, out_path, shard=shard, multiplier=multiplier):
        return Path(out_path)
    config = runnable_config(job, run)
    if threads is not None:
        import torch

        torch.set_num_threads(int(threads))
    # The workflow keeps the previous shard in place while its job runs (Snakemake's
    # update(): put back if the job fails); the new one replaces it atomically.
    path = simulate_shard(
        config, scene, shard, out_path, multiplier=multiplier, progress=False, overwrite=True
    )
    if cache:
        put_in_cache(cache, scene, key, path)
    return path
