"""subslope: the effective density slope γ of dark-matter subhalos from strong-lensing
images, measured with a neural likelihood-ratio estimator (Zhang, Şengül & Dvorkin 2023).

Module map (a module imports only from rooms above it in this list):

====================  ==========================================================
``config``            load and validate a campaign configuration (the schema holds
                      every default); ``ragged``, ``devices``, ``logs``, ``_version``
``physics``           pure lensing math: ``profiles`` (EPL, NFW, tNFW, shear,
                      multipoles, sheet), ``pairs`` (fused member-pair kernels),
                      ``light``, ``cosmology``, ``raytrace``, ``concentration``,
                      ``grid``, ``instrument`` (PSF, convolution, noise)
``stats``             stacking, MLE, test statistic, intervals, calibration
``render``            the batched renderer: settings, pipeline, population passes,
                      compiled kernels, the near/far split
``io``                files: shards, profiles, HST observations, COSMOS, PSF,
                      checksummed resources, atomic writes
``simulation``        priors, scenes, subhalo and line-of-sight populations, shards
``nre``               the likelihood-ratio estimator: data, whitening, models, loss,
                      training, evaluation on the γ grid
``validation``        stiff cases and the lenstronomy reference adapter
``figures``           every figure of the campaign and its saver
``stages``            one module per workflow stage (what ``workflow/scripts`` call)
``cli``               the ``subslope`` command
====================  ==========================================================

The entry points below are imported lazily, so ``import subslope`` stays cheap (the
workflow's planning imports neither torch nor h5py).
"""

from __future__ import annotations

import importlib
from typing import Any

from subslope._version import __version__

#: public name -> module that defines it
_ENTRY_POINTS = {
    "load_config": ("subslope.config", "load"),
    "validate_config": ("subslope.config", "validate"),
    "Scene": ("subslope.simulation.scenes", "Scene"),
    "render": ("subslope.render.pipeline", "render"),
    "RenderSettings": ("subslope.render.pipeline", "RenderSettings"),
    "simulate_shard": ("subslope.simulation.shard", "simulate_shard"),
    "RatioEstimator": ("subslope.nre.models", "RatioEstimator"),
    "interval": ("subslope.stats.intervals", "interval"),
}

__all__ = ["__version__", *_ENTRY_POINTS]


def __getattr__(name: str) -> Any:
    if name in _ENTRY_POINTS:
        module, attr = _ENTRY_POINTS[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'subslope' has no attribute {name!r}")
