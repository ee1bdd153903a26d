"""The observation of a config: its detector (:class:`subslope.physics.instrument.Instrument`),
its PSF kernel (the empirical F814W library or the Gaussian fallback), and the lens-light
fit of estimator inputs made with them (:func:`fit_input_light_of`)."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from subslope.io.observations import find_lens_centre
from subslope.physics.instrument import Instrument, gaussian_psf, load_empirical_psf
from subslope.physics.light.subtract import fit_input_light, model_images

__all__ = ["build_instrument", "build_psf", "fit_input_light_of", "fitted_light_models"]


def build_instrument(config: Mapping[str, Any]) -> Instrument:
    """The detector of ``instrument`` (exposure, gain, read noise, sky, zero point, the
    drizzled noise's pixel correlation)."""
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
        noise_correlation=inst["noise_correlation"],  # a range becomes a tuple there
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


def fit_input_light_of(
    config: Mapping[str, Any], images, theta_e, psf: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """The lens-light fit of ``images`` ``(B, H, W)`` (e⁻/s) that lens-light-subtracted
    inputs use, the same for simulated images and HST cutouts: started at the light
    centre measured with ``hst.lens_centre``, arcs masked about ``theta_e`` ``(B,)``
    (arcsec), with the config's PSF (or ``psf``) and detector noise
    (:func:`subslope.physics.light.subtract.fit_input_light`)."""
    images = np.asarray(images)
    inst = build_instrument(config)
    lc = config["hst"]["lens_centre"]
    centres = np.array(
        [find_lens_centre(im, pixel_scale=inst.pixel_scale, **lc) for im in images]
    ).reshape(-1, 2)
    return fit_input_light(
        images,
        centres,
        theta_e,
        build_psf(config) if psf is None else psf,
        background_sigma=inst.background_sigma,
        exposure_time=inst.total_exposure_time,
        pixel_scale=inst.pixel_scale,
    )


def fitted_light_models(
    config: Mapping[str, Any], images, theta_e, psf: np.ndarray | None = None
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """:func:`fit_input_light_of` and the fitted lens light as images ``(B, H, W)``
    float32 (e⁻/s per pixel): what a lens-light-subtracting estimator takes from images
    that have no stored fit (the stream, the HST cutouts)."""
    psf = build_psf(config) if psf is None else psf
    fit = fit_input_light_of(config, images, theta_e, psf)
    npix, scale = np.shape(images)[-1], build_instrument(config).pixel_scale
    return fit, model_images(fit, psf, npix, scale)
