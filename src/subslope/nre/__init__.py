"""Neural likelihood-ratio estimation of the subhalo slope γ (SCIENCE.md §7).

- :mod:`~subslope.nre.preprocess`: whitening + circular mask, shared by all paths.
- :mod:`~subslope.nre.models`: ResNet ratio estimator ``f(γ, x) = ln r̂(x|γ)``.
- :mod:`~subslope.nre.loss`: NRE / balanced-NRE binary cross-entropy.
- :mod:`~subslope.nre.data`: streaming, reproducibly shuffled batches from HDF5 shards.
- :mod:`~subslope.nre.train`: resumable training loop and the ``model.pt`` artifact.
"""

from .loss import NRELoss, negative_indices, nre_loss
from .models import PRESETS, RatioEstimator, ResNetTrunk, build_model, model_card
from .preprocess import preprocess, read_whitening

__all__ = [
    "NRELoss",
    "negative_indices",
    "nre_loss",
    "PRESETS",
    "RatioEstimator",
    "ResNetTrunk",
    "build_model",
    "model_card",
    "preprocess",
    "read_whitening",
]

from .data import ShardBatches, make_loader  # noqa: E402
from .train import load_estimator, train  # noqa: E402

__all__ += ["ShardBatches", "make_loader", "load_estimator", "train"]
