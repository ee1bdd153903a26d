"""The observation of a config: its detector (:class:`subslope.physics.instrument.Instrument`)
and its PSF kernel (the empirical F814W library or the Gaussian fallback)."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from subslope.physics.instrument import Instrument, gaussian_psf, load_empirical_psf

__all__ = ["build_instrument", "build_psf"]


def build_instrument(config: Mapping[str, Any]) -> Instrument:
    """The detector of ``instrument`` (exposure, gain, read noise, sky, zero point)."""
    inst = config["instrument"]
    return Instrument(
        exposure_time=float(inst["exposure_time"]),
        ccd_gain=float(inst["ccd_gain"]),
        read_noise=float(inst["read_noise"]),
        sky_brightness=float(inst["sky_brightness"]),
        magnitude_zero_point=float(inst["zero_point"]),
        num_exposures=int(inst["num_exposures"]),
        pixel_scale=float(inst["pixel_scale"]),
        psf_fwhm=float(inst["psf"]["fwhm"]),
    )


def build_psf(
    config: Mapping[str, Any], *, resources_dir: str | os.PathLike[str] | None = None
) -> np.ndarray:
    """PSF kernel (float64, sum 1) from ``instrument.psf``: the empirical file under the
    resources folder, or the Gaussian fallback."""
    inst = config["instrument"]
    psf = inst["psf"]
    if psf["source"] == "gaussian":
        return gaussian_psf(psf["fwhm"], inst["pixel_scale"], dtype=torch.float64).numpy()
    folder = Path(resources_dir if resources_dir is not None else config["data"]["resources_dir"])
    path = folder / psf["file"]
    if not path.is_file():
        raise FileNotFoundError(
            f"PSF file {path} (instrument.psf.file under data.resources_dir) not found"
        )
    which = "mean" if psf["index"] is None else int(psf["index"])
    return load_empirical_psf(
        path, which, supersampling=int(psf["supersampling"]), dtype=torch.float64
    ).numpy()
