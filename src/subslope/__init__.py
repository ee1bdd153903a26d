"""subslope: the effective density slope γ of dark-matter subhalos from strong-lensing
images, measured with a neural likelihood-ratio estimator (Zhang, Şengül & Dvorkin 2023).

The package is built in layers of rooms (``physics`` … ``cli``), each importing only from
the layers below it; the map of rooms and modules is docs/index.md (the one copy,
checked against the package by tests/test_layout.py).

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
