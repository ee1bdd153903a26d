"""Stage ``simulate``: image shards, the whitening statistics of the training shards and
the scene example figures (rules simulate_shard, simulate_cdm_shard, compute_whitening,
plot_scene_examples)."""

from __future__ import annotations

import copy
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from subslope.figures.data import plot_scene_examples_from_shard
from subslope.nre.whitening import compute_whitening
from subslope.simulation.shard import simulate_shard
from subslope.stages.plan import RUN_ONLY_RENDER_KEYS

__all__ = [
    "simulate_shard",
    "simulate_shard_job",
    "compute_whitening",
    "plot_scene_examples_from_shard",
]


def simulate_shard_job(
    job: Mapping[str, Any],
    run: Mapping[str, Any],
    scene: str,
    shard: int,
    out_path: str | os.PathLike[str],
    *,
    multiplier: float | None = None,
) -> Path:
    """One shard job of the workflow: ``job`` is its resolved configuration
    (:func:`subslope.stages.plan.shard_job_config`, the rule's params); ``run`` the
    workflow's config, from which only the values that must not rerun a finished shard
    are taken (``data``: where the resources live; ``simulation.render.batch_size`` and
    ``device``)."""
    config = copy.deepcopy(dict(job))
    config["data"] = copy.deepcopy(run["data"])
    render = run["simulation"]["render"]
    config["simulation"]["render"].update({k: render[k] for k in RUN_ONLY_RENDER_KEYS})
    # The workflow keeps the previous shard in place while its job runs (Snakemake's
    # update(): put back if the job fails); the new one replaces it atomically.
    return simulate_shard(
        config, scene, shard, out_path, multiplier=multiplier, progress=False, overwrite=True
    )
