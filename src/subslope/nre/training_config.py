"""The training section of a campaign: its defaults (from the config schema, their
only home), its checks and its hash. Pure Python: the workflow plans training jobs
with it without importing torch.
"""

from __future__ import annotations

import copy
import hashlib
import json
from collections.abc import Mapping
from typing import Any

from subslope.config import schema_defaults

#: Values of ``training.augment`` (:mod:`subslope.nre.augment`, which needs torch).
AUGMENTATIONS = ("none", "dihedral")

__all__ = [
    "WORKFLOW_KEYS",
    "RESUME_SAFE_KEYS",
    "training_defaults",
    "resolve_config",
    "config_hash",
]

#: Keys of the config's ``training`` section that steer the workflow (where and with
#: what resources the job runs), not the optimisation.
WORKFLOW_KEYS = ("device", "threads", "gpus", "ranks", "mem_mb", "runtime")

#: Keys that may differ between an interrupted run and its resumption.
RESUME_SAFE_KEYS = frozenset(
    {
        "max_epochs",
        "early_stop_patience",
        "num_workers",
        "checkpoint_every",
        "max_steps",
        "progress",
        "val_batch_size",
    }
)


def training_defaults() -> dict[str, Any]:
    """Every key of a training configuration with its default: the schema's ``training``
    section without :data:`WORKFLOW_KEYS` (null ``arch`` keys dropped, so the preset
    decides them), plus ``pixel_scale`` (the instrument's), ``progress`` (a progress bar,
    on) and ``seed`` 0 where the schema leaves it to the workflow (null: derived from
    the global seed)."""
    out = {k: v for k, v in schema_defaults("training").items() if k not in WORKFLOW_KEYS}
    out["arch"] = {k: v for k, v in schema_defaults("training.arch").items() if v is not None}
    out["seed"] = 0 if out.get("seed") is None else out["seed"]
    out["pixel_scale"] = schema_defaults("instrument")["pixel_scale"]
    out["progress"] = True
    return out


def resolve_config(config: Mapping[str, Any] | None) -> dict[str, Any]:
    """The training section with defaults filled in; unknown keys raise ``ValueError``."""
    cfg = training_defaults()
    config = dict(config or {})
    unknown = set(config) - set(cfg)
    if unknown:
        raise ValueError(f"training: unknown key(s) {sorted(unknown)}; allowed: {sorted(cfg)}")
    cfg.update(copy.deepcopy(config))
    for key in (
        "batch_size",
        "max_epochs",
        "lr_patience",
        "lr_cooldown",
        "early_stop_patience",
        "block_size",
        "shuffle_window",
    ):
        v = cfg[key]
        low = 0 if key in ("lr_patience", "lr_cooldown") else 1
        if isinstance(v, bool) or not isinstance(v, int) or v < low:
            raise ValueError(f"training.{key} must be an integer >= {low}, got {v!r}")
    if cfg["batch_size"] < 2:
        raise ValueError(
            f"training.batch_size must be >= 2 (negatives are formed within a batch), "
            f"got {cfg['batch_size']}"
        )
    if cfg["data"] not in ("shards", "stream"):
        raise ValueError(f"training.data must be 'shards' or 'stream', got {cfg['data']!r}")
    if cfg["augment"] not in AUGMENTATIONS:
        raise ValueError(
            f"training.augment must be one of {', '.join(AUGMENTATIONS)}; got {cfg['augment']!r}"
        )
    if cfg["amp"] not in ("auto", "bf16", "fp16", "off"):
        raise ValueError(f"training.amp must be one of auto, bf16, fp16, off; got {cfg['amp']!r}")
    if not (
        cfg["lr"] > 0
        and cfg["weight_decay"] >= 0
        and 0 < cfg["lr_factor"] < 1
        and cfg["min_delta"] >= 0
    ):
        raise ValueError(
            "training: need lr > 0, weight_decay >= 0, 0 < lr_factor < 1, min_delta >= 0; got "
            f"lr={cfg['lr']!r}, weight_decay={cfg['weight_decay']!r}, "
            f"lr_factor={cfg['lr_factor']!r}, "
            f"min_delta={cfg['min_delta']!r}"
        )
    return cfg


def config_hash(cfg: Mapping[str, Any]) -> str:
    """SHA-256 (16 hex digits) of the training section without the resume-safe keys."""
    core = {k: v for k, v in cfg.items() if k not in RESUME_SAFE_KEYS}
    return hashlib.sha256(json.dumps(core, sort_keys=True, default=str).encode()).hexdigest()[:16]
