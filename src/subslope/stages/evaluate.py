"""Stage ``evaluate``: ln r̂(x|γ) of every image of a shard on the γ grid, written as a
profiles file (rules evaluate_profiles, evaluate_cdm_profiles)."""

from __future__ import annotations

import os
from pathlib import Path

from subslope.io.ratio_profiles import write_profiles
from subslope.io.shards import open_shard
from subslope.nre.evaluate import estimator_profiles
from subslope.nre.inputs import InputTransform, ShardLightModels

__all__ = ["PROFILE_PARAMS", "evaluate_shard"]

#: Per-image parameters of a shard kept beside its profiles (None where the shard has none).
PROFILE_PARAMS = ("theta_e", "lens_x", "lens_y", "gamma_sub", "set_index", "c_multiplier")


def evaluate_shard(
    model_path,
    shard_path,
    out_path,
    *,
    gammas,
    batch_size: int = 64,
    device: str = "auto",
    run_name: str = "",
) -> Path:
    """ln r̂ of every image of a shard on the grid ``gammas``, written with
    :func:`write_profiles`."""
    from subslope.nre.train import load_estimator

    model, meta = load_estimator(model_path)
    needs_light = InputTransform.from_json(meta.get("inputs")).needs_light
    with open_shard(shard_path) as shard:
        params = {k: shard.params.get(k) for k in PROFILE_PARAMS}
        light = ShardLightModels(shard_path, shard.file) if needs_light else None
        scene = shard.attrs.get("scene", "")
        profiles = estimator_profiles(
            model,
            meta,
            shard.images,
            params["theta_e"],
            params["lens_x"],
            params["lens_y"],
            gammas,
            batch_size=batch_size,
            device=device,
            light=light,
        )
    attrs = {
        "scene": str(scene),
        "shard": os.fspath(shard_path),
        "model": os.fspath(model_path),
        "model_config_hash": str(meta.get("config_hash", "")),
        "run_name": run_name,
    }
    return write_profiles(
        out_path,
        log_ratio=profiles,
        gammas=gammas,
        gamma_true=params["gamma_sub"],
        set_index=params["set_index"],
        c_multiplier=params["c_multiplier"],
        theta_e=params["theta_e"],
        lens_x=params["lens_x"],
        lens_y=params["lens_y"],
        attrs=attrs,
    )
