"""The trained estimator on the γ grid: ``ln r̂(x|γ_g)`` of every image (float64).

Images go through the same pre-processing as in training (the input transform of
:mod:`subslope.nre.inputs`, whitening with the training statistics and the circular
mask of ``mask_factor`` × θ_E about the lens centre,
:mod:`subslope.nre.preprocess`); the trunk runs once per image and the head on every
(image, γ) pair (:meth:`subslope.nre.models.RatioEstimator.log_ratio_grid`). An
estimator trained with ``augment: dihedral`` is evaluated on the eight symmetric views
of every image and its ln r̂ averaged (``symmetrize``).
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from subslope.devices import pick_device
from subslope.nre.augment import N_DIHEDRAL, dihedral
from subslope.nre.inputs import InputTransform
from subslope.nre.preprocess import preprocess, read_whitening
from subslope.nre.training_config import training_defaults
from subslope.physics.instrument import PIXEL_SCALE
from subslope.stats.intervals import check_grid

__all__ = ["log_ratio_profiles", "estimator_profiles"]


def _check_call(inputs: InputTransform, light, images, batch_size) -> None:
    if inputs.needs_light and (light is None or len(light) != len(images)):
        raise ValueError(
            "inputs 'light_subtracted' need the fitted lens-light model of every image"
        )
    if int(batch_size) != batch_size or batch_size < 1:
        raise ValueError(f"batch_size must be a positive integer, got {batch_size!r}")


def log_ratio_profiles(
    model,
    images,
    theta_e,
    lens_x,
    lens_y,
    whitening,
    gammas,
    *,
    batch_size: int = 64,
    device=None,
    pixel_scale: float = PIXEL_SCALE,
    mask_factor: float | None = 1.5,
    inputs: InputTransform | None = None,
    light=None,
    symmetrize: bool = False,
) -> np.ndarray:
    """``ln r̂(x_b|γ_g)`` of every image on the grid: ``(B, G)`` float64.

    ``model``: a :class:`subslope.nre.RatioEstimator` (:func:`subslope.nre.load_estimator`),
    moved to ``device`` (None: CUDA when available, else CPU, at call time) in eval mode.
    ``images``: ``(B, H, W)`` raw images (e⁻/s per pixel), anything sliceable along the
    first axis (numpy array, h5py dataset), read ``batch_size`` at a time (the trunk runs
    once per image, the head on B × G pairs). ``theta_e, lens_x, lens_y``: ``(B,)`` or
    scalars, arcsec, for the mask. ``whitening``: ``(mean, std)``, a mapping or a JSON
    path (:func:`subslope.nre.read_whitening`; a checkpoint's ``metadata["whitening"]``).
    ``gammas``: the 1-D grid (:func:`subslope.stats.intervals.gamma_grid`).
    ``pixel_scale, mask_factor``: pre-processing, the checkpoint's
    ``metadata["preprocess"]``. ``inputs, light``: the input transform (None: the pixels
    as given) and, where it subtracts the lens light, every image's fitted model (sliced
    like ``images``). ``symmetrize``: average ln r̂ over the eight symmetric views of
    every pre-processed image (:func:`_log_ratio`; eight trunk passes an image).
    """
    g = check_grid(gammas)
    inputs = inputs or InputTransform()
    _check_call(inputs, light, images, batch_size)
    n = len(images)
    geometry = [np.full(n, v, dtype=np.float64) for v in (theta_e, lens_x, lens_y)]
    prep = dict(inputs=inputs, whitening=read_whitening(whitening), pixel_scale=pixel_scale)
    prepare = functools.partial(_prepared, geometry=geometry, mask_factor=mask_factor, **prep)
    dev = pick_device(device, key="inference.device")
    model = model.to(dev).eval()
    dtype = next(model.parameters()).dtype
    grid_t = torch.as_tensor(g, dtype=dtype, device=dev)
    out = np.empty((n, g.size), dtype=np.float64)
    with torch.inference_mode():
        for s in range(0, n, int(batch_size)):
            part = slice(s, min(s + int(batch_size), n))
            x = prepare(images[part], light[part] if inputs.needs_light else None, part)
            out[part] = _log_ratio(
                model, torch.as_tensor(x, dtype=dtype, device=dev), grid_t, symmetrize
            )
    return out


def _prepared(
    images, light, part: slice, *, geometry, inputs, whitening, pixel_scale, mask_factor
) -> np.ndarray:
    """One batch of raw images ``(b, H, W)`` (the slice ``part`` of the set) as the
    network sees them: the input transform (``light``: the fitted lens light, where it
    is subtracted), whitened and masked (:func:`subslope.nre.preprocess.preprocess`;
    ``geometry``: θ_E, lens x and y of every image of the set)."""
    x = np.asarray(images, dtype=np.float32)
    if x.ndim != 3:
        raise ValueError(f"images must have shape (B, H, W), got a batch of shape {x.shape}")
    theta_e, lens_x, lens_y = (v[part] for v in geometry)
    return preprocess(
        inputs.apply(x, light),
        theta_e,
        lens_x,
        lens_y,
        *whitening,
        pixel_scale=pixel_scale,
        mask_factor=mask_factor,
    )


def _log_ratio(model, x, grid, symmetrize: bool) -> np.ndarray:
    """ln r̂ of the pre-processed batch ``x`` on ``grid``, float64; with ``symmetrize``
    the mean over the eight symmetric views of every image (:mod:`subslope.nre.augment`):
    for an estimator trained with ``augment: dihedral`` the true ln r is the same for all
    eight, so their mean is a lower-variance estimate of it."""
    if not symmetrize:
        return model.log_ratio_grid(x, grid).double().cpu().numpy()
    views = [model.log_ratio_grid(dihedral(x, k), grid) for k in range(N_DIHEDRAL)]
    return torch.stack(views).double().mean(0).cpu().numpy()


def estimator_profiles(
    model,
    meta,
    images,
    theta_e,
    lens_x,
    lens_y,
    gammas,
    *,
    batch_size: int = 64,
    device=None,
    pixel_scale: float | None = None,
    light=None,
) -> np.ndarray:
    """:func:`log_ratio_profiles` with the input transform, whitening and pre-processing
    the estimator was trained with (``meta`` of :func:`subslope.nre.train.load_estimator`),
    averaged over the eight symmetries of the grid when it was trained with them
    (``training.augment: dihedral``);
    ``light``: the fitted lens light of every image, for an estimator of lens-light-
    subtracted inputs. A model file without pre-processing metadata falls back on
    ``pixel_scale`` (if given) and on the training defaults of the config schema."""
    defaults = training_defaults()
    prep = meta.get("preprocess", {})
    fallback = defaults["pixel_scale"] if pixel_scale is None else pixel_scale
    return log_ratio_profiles(
        model,
        images,
        theta_e,
        lens_x,
        lens_y,
        meta["whitening"],
        gammas,
        batch_size=batch_size,
        device=None if device in (None, "auto") else device,
        pixel_scale=prep.get("pixel_scale", fallback),
        mask_factor=prep.get("mask_factor", defaults["mask_factor"]),
        inputs=InputTransform.from_json(meta.get("inputs")),
        light=light,
        symmetrize=(meta.get("config") or {}).get("augment", "none") == "dihedral",
    )
