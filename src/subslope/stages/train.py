"""Stage ``train``: the estimator's training section from the config, the checkpoint
key and the training run (rule train_estimator)."""

from __future__ import annotations

import copy
import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from subslope.nre.training_config import WORKFLOW_KEYS, config_hash, resolve_config
from subslope.stages.plan import derived_seed

__all__ = ["training_section", "checkpoint_key", "data_fingerprint", "run_training"]


def training_section(config: Mapping[str, Any]) -> dict[str, Any]:
    """The ``subslope.nre.train`` config from the workflow config (validated, defaults filled).

    ``seed: null`` becomes a seed derived from the global seed; ``arch`` keys that are
    null take the preset's value; the pixel scale comes from ``instrument``; workflow-only
    keys (device, threads, gpus, mem_mb, runtime) are dropped; no progress bar.
    """
    tr = copy.deepcopy(dict(config["training"]))
    for key in WORKFLOW_KEYS:
        tr.pop(key, None)
    tr["arch"] = {k: v for k, v in dict(tr.get("arch") or {}).items() if v is not None}
    if tr.get("seed") is None:
        tr["seed"] = derived_seed(config["seed"], "training")
    tr["pixel_scale"] = float(config["instrument"]["pixel_scale"])
    tr["progress"] = False
    return tr


def checkpoint_key(
    training: Mapping[str, Any],
    train_shards: Sequence,
    val_shards: Sequence,
    data_hashes: Mapping[str, str] | None = None,
) -> str:
    """12 hex digits naming the checkpoint folder of one training run.

    Depends on the training section (without the resume-safe keys) and on the data
    (shard paths and the simulation hashes of their scenes), so a restarted job with the
    same inputs resumes while a changed config or data starts a fresh folder.
    """
    payload = {
        "training": config_hash(resolve_config(training)),
        "train": [os.fspath(p) for p in train_shards],
        "val": [os.fspath(p) for p in val_shards],
        "data": dict(data_hashes or {}),
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:12]


def data_fingerprint(train_shards: Sequence, val_shards: Sequence, whitening) -> str:
    """12 hex digits of the SHA-256 of every training and validation shard's bytes and of
    the whitening JSON. Refuses a whitening file whose recorded shard checksums are not
    those of ``train_shards`` now (it was computed from other images); a shard that
    changed because it is corrupt is named as such (:func:`subslope.io.shards.verify_shard`)."""
    from subslope.io.atomic import read_json
    from subslope.io.shards import file_sha256, verify_shard

    sums = {os.fspath(p): file_sha256(p) for p in [*train_shards, *val_shards]}
    if isinstance(whitening, (str, os.PathLike)):
        recorded = read_json(whitening).get("shards") or []
        stale = [
            r["path"]
            for r in recorded
            if r.get("path") in sums and r.get("sha256") not in (None, sums[r["path"]])
        ]
        for path in stale:  # a corrupt shard is named as such, not as a stale whitening
            verify_shard(path)
        if stale:
            raise ValueError(
                f"whitening file {os.fspath(whitening)} was computed from other contents of "
                f"{stale}; rerun its rule (snakemake -R compute_whitening) before training"
            )
        sums["whitening"] = file_sha256(whitening)
    return hashlib.sha256(json.dumps(sums, sort_keys=True).encode()).hexdigest()[:12]


def run_training(
    training: Mapping[str, Any],
    train_shards: Sequence,
    val_shards: Sequence,
    whitening,
    out_dir,
    ckpt_dir,
    *,
    device: str = "auto",
) -> dict[str, Any]:
    """Train (resuming from ``ckpt_dir`` when possible); ``out_dir`` gets model.pt +
    training_log.csv.

    The checkpoints live in ``ckpt_dir/data-<fingerprint>`` (:func:`data_fingerprint`):
    shards whose content changed under the same paths and config start a fresh run
    instead of resuming one trained on other images."""
    from subslope.nre.train import train

    dev = None if device in (None, "auto") else device
    ckpt = Path(ckpt_dir) / f"data-{data_fingerprint(train_shards, val_shards, whitening)}"
    summary = train(
        training, list(train_shards), list(val_shards), whitening, out_dir, ckpt, device=dev
    )
    if not summary["finished"]:
        raise RuntimeError(
            f"training stopped before the end ({summary}); run again to resume from {ckpt_dir}"
        )
    return summary
