"""Training checkpoints and estimator files: atomic saves, reads that name a bad file,
and the random states stored in them.

The random states are kept as plain tensors and lists, so that
``torch.load(weights_only=True)`` can read them back.
"""

from __future__ import annotations

import os
import random
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from subslope.io.atomic import atomic_write

if TYPE_CHECKING:
    from .models import RatioEstimator

__all__ = [
    "load_estimator",
    "CheckpointError",
    "atomic_save",
    "rng_state",
    "set_rng_state",
    "torch_load",
]


class CheckpointError(ValueError):
    """A checkpoint or estimator file cannot be read (truncated, corrupt, not ours)."""


def torch_load(path, map_location, recovery: str) -> dict[str, Any]:
    """``torch.load`` of a file of ours; a file that cannot be read raises
    :class:`CheckpointError` naming it, its size and ``recovery``."""
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as exc:  # torch reports a bad zip, EOF, pickle errors, ... alike
        size = os.path.getsize(path) if os.path.exists(path) else 0
        raise CheckpointError(
            f"{os.fspath(path)} ({size} bytes) cannot be read: truncated or corrupt "
            f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}); "
            f"{recovery}"
        ) from None


def rng_state() -> dict[str, Any]:
    name, keys, pos, has_gauss, cached = np.random.get_state()
    py = random.getstate()
    state = {
        "torch": torch.get_rng_state(),
        "numpy": [
            name,
            torch.from_numpy(keys.astype(np.int64)),
            int(pos),
            int(has_gauss),
            float(cached),
        ],
        "python": [py[0], list(py[1]), py[2]],
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: Mapping[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, keys.numpy().astype(np.uint32), pos, has_gauss, cached))
    py = state["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def atomic_save(obj, path: Path) -> None:
    with atomic_write(path) as tmp:
        torch.save(obj, tmp)


def load_estimator(path, *, map_location="cpu") -> tuple[RatioEstimator, dict[str, Any]]:
    """Rebuild the trained estimator from ``model.pt``: ``(model in eval mode, metadata)``.

    ``metadata`` holds every entry of the file but the weights: ``model_card``,
    ``whitening`` ({mean, std}), ``gamma_norm``, ``preprocess`` ({pixel_scale,
    mask_factor}), ``config``, ``config_hash``, ``history``, ``best_epoch``, ...
    """
    from .models import build_model

    payload = torch_load(
        path,
        map_location,
        "delete it and run snakemake again to write it anew (training resumes from its "
        "checkpoints)",
    )
    if payload.get("format") != "subslope.nre/1":
        raise ValueError(
            f"{os.fspath(path)!r} is not a subslope estimator file (format "
            f"{payload.get('format')!r})"
        )
    card = payload["model_card"]
    model = build_model(card["arch"], gamma_mean=card["gamma_mean"], gamma_std=card["gamma_std"])
    model.load_state_dict(payload["model"])
    model.eval()
    meta = {k: v for k, v in payload.items() if k != "model"}
    return model, meta
