"""The lens-light fit behind lens-light-subtracted estimator inputs, and its model images.

With ``training.inputs: light_subtracted`` the estimator sees ``image − model``, where
``model`` is the PSF-convolved elliptical Sérsic plus pedestal of
:func:`subslope.physics.light.fit.fit_lens_light` fitted to that very image: the same
code and settings (:data:`INPUT_FIT`) for every simulated image (in its shard job) and for
the HST cutouts, never the true simulated light. The fitted parameters are stored with the
images (:data:`STORED`); :func:`model_images` rebuilds the model from them, so no
consumer refits.

The settings are the fast ones of docs/realism.md: model in float32 (normal equations in
float64), 4 Levenberg–Marquardt steps per pass, images fitted in chunks of
:data:`CHUNK` (larger batches are slower per image on a CPU: their working set leaves
the cache). On simulated lenses their recovery equals the float64, 10-step reference.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from subslope.physics.grid import pixel_grid
from subslope.physics.light.fit import PARAMS, fit_lens_light, sersic_model

__all__ = ["INPUT_FIT", "CHUNK", "STORED", "fit_input_light", "model_images"]

#: The dtype of the fit's model images (its normal equations are float64).
MODEL_DTYPE = torch.float32
#: Keyword arguments of :func:`~subslope.physics.light.fit.fit_lens_light` for inputs.
INPUT_FIT: dict[str, Any] = {
    "arc_mask": (0.6, 1.5),
    "clip": 3.0,
    "systematic": 0.02,
    "iterations": 4,
    "pedestal": True,
    "dtype": MODEL_DTYPE,
}
#: Images fitted at once.
CHUNK = 200
#: Stored per image: the fit's parameters (AB mag, arcsec, -, -, -, arcsec, arcsec,
#: e⁻/s per pixel) and its χ² per unmasked pixel.
STORED = ("mag", "r_sersic", "n_sersic", "e1", "e2", "x", "y", "background", "chi2_dof")


def fit_input_light(
    images,
    centres,
    theta_e,
    psf,
    *,
    background_sigma: float,
    exposure_time: float,
    pixel_scale: float,
) -> dict[str, np.ndarray]:
    """Fit every image of ``images`` ``(B, H, W)`` (e⁻/s per pixel) with :data:`INPUT_FIT`,
    started at ``centres`` ``(B, 2)`` (arcsec) with the arc annulus at ``theta_e`` ``(B,)``;
    returns the arrays :data:`STORED`, each ``(B,)`` float64."""
    images = np.asarray(images)
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
    theta_e = np.asarray(theta_e, dtype=np.float64).reshape(-1)
    if not images.shape[0] == centres.shape[0] == theta_e.shape[0]:
        raise ValueError(
            f"images {images.shape}, centres {centres.shape} and theta_e {theta_e.shape} "
            "do not describe the same images"
        )
    parts: dict[str, list[np.ndarray]] = {k: [] for k in STORED}
    for s in range(0, images.shape[0], CHUNK):
        fit = fit_lens_light(
            images[s : s + CHUNK],
            psf,
            centres[s : s + CHUNK],
            theta_e[s : s + CHUNK],
            background_sigma=background_sigma,
            exposure_time=exposure_time,
            pixel_scale=pixel_scale,
            **INPUT_FIT,
        )
        for k in STORED:
            parts[k].append(np.asarray(getattr(fit, k), dtype=np.float64))
    if not parts["mag"]:
        return {k: np.zeros(0) for k in STORED}
    return {k: np.concatenate(v) for k, v in parts.items()}


def model_images(params, psf, npix: int, pixel_scale: float) -> np.ndarray:
    """The fitted lens light ``(B, npix, npix)`` float32 (e⁻/s per pixel) of stored fit
    parameters ``params`` (the keys of :data:`STORED` but ``chi2_dof``, arrays ``(B,)``),
    evaluated in the float32 of the fit."""
    missing = [k for k in STORED[:-1] if k not in params]
    if missing:
        raise ValueError(f"lens-light fit parameters {missing} are missing")
    cols = {k: np.asarray(params[k], dtype=np.float64).reshape(-1) for k in STORED[:-1]}
    r = cols["r_sersic"]
    if not np.all(np.isfinite(np.stack(list(cols.values())))) or np.any(r <= 0):
        raise ValueError("lens-light fit parameters must be finite, with r_sersic > 0")
    theta = np.stack(
        [cols[k] for k in ("mag",)]
        + [np.log(r)]
        + [cols[k] for k in ("n_sersic", "e1", "e2", "x", "y", "background")],
        axis=1,
    )
    assert theta.shape[1] == len(PARAMS)
    dtype = MODEL_DTYPE
    xs, ys = (g.to(dtype) for g in pixel_grid(int(npix), float(pixel_scale), dtype=torch.float64))
    psf_t = torch.as_tensor(np.asarray(psf, dtype=np.float64)).to(dtype)
    out = np.empty((theta.shape[0], int(npix), int(npix)), dtype=np.float32)
    for s in range(0, theta.shape[0], CHUNK):
        t = torch.as_tensor(theta[s : s + CHUNK]).to(dtype)
        out[s : s + CHUNK] = sersic_model(t, (xs[None], ys[None]), psf_t, pixel_scale).numpy()
    if not np.all(np.isfinite(out)):
        raise ValueError("lens-light model images are not finite")
    return out
