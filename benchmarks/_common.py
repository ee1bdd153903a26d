"""Shared helpers of the performance benchmarks.

- :func:`make_scene`: :func:`subslope.validation.scenes.make_scene` (a batch of sampled
  scenes: train / nfw / tnfw presets, Sérsic source, fixed N_sub, optional LoS) seen
  through the empirical F814W PSF;
- the lenstronomy reference model of the same parameters is
  :func:`subslope.validation.lenstronomy.lenstronomy_model` (the one adapter);
- :func:`image_errors` comes from :mod:`subslope.validation.scenes`;
  :func:`reference_settings` and :func:`psf_kernel` from ``benchmarks/render_speed.py``.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import render_speed as _rs  # noqa: E402  (reuse: PSF, error metrics, reference settings)

from subslope.validation import scenes as _scenes  # noqa: E402

psf_kernel = _rs.psf_kernel
reference_settings = _rs.reference_settings
Batch = _scenes.Batch
image_errors = _scenes.image_errors
one_image = _scenes.one_image

__all__ = [
    "Batch",
    "make_scene",
    "one_image",
    "psf_kernel",
    "image_errors",
    "reference_settings",
    "machine_info",
    "load",
]


def load() -> str:
    """1/5/15-minute load average, formatted."""
    return "{:.2f}/{:.2f}/{:.2f}".format(*os.getloadavg())


def machine_info() -> dict:
    cpu = "unknown"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        import lenstronomy

        lv = lenstronomy.__version__
    except ImportError:  # pragma: no cover
        lv = "not installed"
    try:
        up = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    except OSError:  # pragma: no cover
        up = load()
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "lenstronomy": lv,
        "uptime": up,
        "torch_threads": torch.get_num_threads(),
        "cuda": torch.cuda.is_available(),
    }


# ----------------------------------------------------------------------------- scenes
def make_scene(*args, **kwargs) -> Batch:
    """:func:`subslope.validation.scenes.make_scene` seen through :func:`psf_kernel`."""
    return _scenes.make_scene(psf_kernel(), *args, **kwargs)
