"""Neural likelihood-ratio estimation of the subhalo slope γ (``docs/estimator.md``).

- :mod:`~subslope.nre.preprocess`: whitening + circular mask, shared by all paths;
  :mod:`~subslope.nre.whitening`: the whitening statistics of the training shards.
- :mod:`~subslope.nre.models`: ResNet ratio estimator ``f(γ, x) = ln r̂(x|γ)``.
- :mod:`~subslope.nre.loss`: NRE / balanced-NRE binary cross-entropy.
- :mod:`~subslope.nre.data`: streaming, reproducibly shuffled batches from HDF5 shards.
- :mod:`~subslope.nre.stream`: batches simulated while training (``training.data: stream``).
- :mod:`~subslope.nre.training_config`: the training section's defaults and hash.
- :mod:`~subslope.nre.train`: resumable training loop and the ``model.pt`` artifact.
- :mod:`~subslope.nre.evaluate`: ``ln r̂`` of images on the γ grid.

The names below are imported lazily (``import subslope.nre.training_config`` needs no torch).
"""

from __future__ import annotations

import importlib
from typing import Any

_NAMES = {
    "NRELoss": "loss",
    "negative_indices": "loss",
    "nre_loss": "loss",
    "PRESETS": "models",
    "RatioEstimator": "models",
    "ResNetTrunk": "models",
    "build_model": "models",
    "model_card": "models",
    "preprocess": "preprocess",
    "read_whitening": "preprocess",
    "ShardBatches": "data",
    "make_loader": "data",
    "batch_tensors": "data",
    "StreamBatches": "stream",
    "load_estimator": "train",
    "train": "train",
    "log_ratio_profiles": "evaluate",
}

__all__ = sorted(_NAMES)


def __getattr__(name: str) -> Any:
    if name in _NAMES:
        return getattr(importlib.import_module(f"subslope.nre.{_NAMES[name]}"), name)
    raise AttributeError(f"module 'subslope.nre' has no attribute {name!r}")
