"""What a training writes besides its checkpoints: ``training_log.csv`` (one row per
epoch) and ``model.pt``, the best weights with everything needed to use them
(:func:`subslope.nre.checkpoints.load_estimator` reads it back). With several ranks, rank 0
alone writes them (:mod:`subslope.nre.train`)."""

from __future__ import annotations

import csv
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from subslope.io.atomic import atomic_write

from .checkpoints import atomic_save, torch_load
from .inputs import InputTransform
from .models import model_card

__all__ = ["LOG_COLUMNS", "write_log", "write_model", "summary"]

LOG_COLUMNS = ("epoch", "train_loss", "val_loss", "lr", "seconds", "images_per_s")


def write_log(history: Sequence[Mapping[str, Any]], path: Path) -> None:
    with atomic_write(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=LOG_COLUMNS)
        w.writeheader()
        for row in history:
            w.writerow({k: row[k] for k in LOG_COLUMNS})


def write_model(run, whitening, inputs: InputTransform, out_dir: Path) -> Path:
    """``model.pt``: the best weights with everything needed to use them."""
    cfg = run.cfg
    best = torch_load(run.best_path, "cpu", f"delete {run.best_path.parent} to train afresh")
    run.model.load_state_dict(best["model"])
    model_path = out_dir / "model.pt"
    atomic_save(
        {
            "format": "subslope.nre/1",
            "model": {k: v.cpu() for k, v in run.model.state_dict().items()},
            "model_card": model_card(run.model),
            "whitening": {"mean": whitening[0], "std": whitening[1]},
            "inputs": inputs.to_json(),
            "gamma_norm": {"mean": float(run.model.gamma_mean), "std": float(run.model.gamma_std)},
            "preprocess": {"pixel_scale": cfg["pixel_scale"], "mask_factor": cfg["mask_factor"]},
            "config": cfg,
            "config_hash": run.chash,
            "history": run.state.history,
            "best_epoch": int(best["epoch"]),
            "best_val_loss": float(best["val_loss"]),
            "stop_reason": run.state.stop_reason,
            "torch_version": str(torch.__version__),
        },
        model_path,
    )
    return model_path


def summary(state, model_path, *, finished: bool) -> dict[str, Any]:
    return {
        "finished": finished,
        "model": model_path,
        "epochs": state.epoch,
        "step": state.step,
        "best_val_loss": state.best_val,
        "stop_reason": state.stop_reason,
    }
