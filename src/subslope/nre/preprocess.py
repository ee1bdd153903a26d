"""Image pre-processing shared by training, inference and the real HST cutouts.

One transform, applied identically everywhere (docs/physics.md):

1. whiten with two scalars measured once on the training set,
   ``x ← (x − mean) / std`` (e⁻/s per pixel → dimensionless);
2. set every pixel whose centre lies farther than ``mask_factor · θ_E`` from the lens
   centre ``(lens_x, lens_y)`` to 0 (after whitening, so masked pixels sit at the
   whitened value 0, not at the whitened value of a zero-flux pixel).

The pixel grid is the package convention (docs/design.md): ``x_i = (i − (n−1)/2)·Δ``,
``image[..., j, i]`` at ``(x_i, y_j)``. A pixel is kept when its centre satisfies
``(x − lens_x)² + (y − lens_y)² ≤ (mask_factor·θ_E)²``.

The whitening statistics are computed by :mod:`subslope.nre.whitening` (workflow rule
``compute_whitening``); :func:`read_whitening` accepts its JSON (keys ``mean`` and
``std``; other keys are ignored), a mapping or a ``(mean, std)`` pair.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence

import numpy as np
import torch

from subslope.io.atomic import read_json
from subslope.physics.instrument import PIXEL_SCALE

from .inputs import InputTransform

__all__ = ["preprocess", "read_whitening", "read_inputs", "Whitening"]

#: A ``(mean, std)`` pair of floats.
Whitening = tuple[float, float]


def read_whitening(source) -> Whitening:
    """Whitening statistics as a ``(mean, std)`` pair of floats.

    ``source`` is a path to a JSON file with keys ``mean`` and ``std``, a mapping with
    those keys, or a ``(mean, std)`` sequence. Raises ``ValueError`` naming the source
    when a key is missing, a value is not finite, or ``std <= 0``.
    """
    where = "whitening"
    if isinstance(source, (str, os.PathLike)):
        where = f"whitening file {os.fspath(source)!r}"
        source = read_json(source)
    if isinstance(source, Mapping):
        missing = [k for k in ("mean", "std") if k not in source]
        if missing:
            raise ValueError(f"{where}: missing key(s) {missing}; expected 'mean' and 'std'")
        mean, std = source["mean"], source["std"]
    elif isinstance(source, Sequence) and len(source) == 2:
        mean, std = source
    else:
        raise ValueError(
            f"{where}: expected a JSON path, a mapping or a (mean, std) pair, got {source!r}"
        )
    mean, std = float(mean), float(std)
    if not (math.isfinite(mean) and math.isfinite(std) and std > 0):
        raise ValueError(f"{where}: need finite mean and std > 0, got mean={mean!r}, std={std!r}")
    return mean, std


def read_inputs(source, expect: str | None = None) -> InputTransform:
    """The input transform a whitening was measured after: its ``inputs`` entry (a JSON
    path or a mapping; a ``(mean, std)`` pair or a file without the entry: ``whitened``).
    ``expect``: the ``training.inputs`` it must have (a clear error otherwise)."""
    if isinstance(source, (str, os.PathLike)):
        source = read_json(source)
    inputs = InputTransform()
    if isinstance(source, Mapping):
        inputs = InputTransform.from_json(source.get("inputs"))
    if expect is not None and inputs.kind != expect:
        raise ValueError(
            f"training.inputs = {expect!r} but the whitening was measured on "
            f"{inputs.kind!r} inputs: recompute it (snakemake -R compute_whitening)"
        )
    return inputs


def _as_tensor(value, *, dtype=None, device=None) -> torch.Tensor:
    if isinstance(value, torch.Tensor):
        return value.to(dtype=dtype or value.dtype, device=device or value.device)
    return torch.as_tensor(np.asarray(value), dtype=dtype, device=device)


def preprocess(
    images,
    theta_e,
    lens_x,
    lens_y,
    mean: float,
    std: float,
    *,
    pixel_scale: float = PIXEL_SCALE,
    mask_factor: float | None = 1.5,
):
    """Whiten and mask lens images.

    Parameters
    ----------
    images:
        ``(..., H, W)`` pixel values in e⁻/s per pixel (numpy array or torch tensor;
        a channel axis, e.g. ``(B, 1, H, W)``, is fine since it is part of ``...``).
    theta_e, lens_x, lens_y:
        Einstein radius and lens centre, arcsec; scalars or per-image arrays. Arrays
        with fewer axes than the leading shape ``...`` of ``images`` are aligned on
        the left, so ``(B,)`` values work with ``(B, H, W)`` and ``(B, 1, H, W)``.
    mean, std:
        Whitening scalars (training-set pixel mean and std, e⁻/s per pixel).
    pixel_scale:
        Pixel size, arcsec.
    mask_factor:
        Keep pixels within ``mask_factor · θ_E`` of the lens centre; ``None`` disables
        the mask (whitening only).

    Returns
    -------
    Same shape as ``images``. A numpy input gives a numpy array, a torch input a
    tensor on the same device. Floating inputs keep their dtype; integer inputs become
    float32.
    """
    is_numpy = not isinstance(images, torch.Tensor)
    x = _as_tensor(images)
    if not torch.is_floating_point(x):
        x = x.to(torch.float32)
    if x.ndim < 2:
        raise ValueError(f"images must have shape (..., H, W), got shape {tuple(x.shape)}")
    if not (math.isfinite(float(std)) and float(std) > 0):
        raise ValueError(f"std must be finite and > 0, got {std!r}")
    if not pixel_scale > 0:
        raise ValueError(f"pixel_scale must be > 0 arcsec, got {pixel_scale!r}")
    out = (x - float(mean)) / float(std)
    if mask_factor is not None:
        if not mask_factor > 0:
            raise ValueError(f"mask_factor must be > 0 or None, got {mask_factor!r}")
        keep = _aperture(x, theta_e, lens_x, lens_y, pixel_scale, mask_factor)
        out = torch.where(keep, out, torch.zeros((), dtype=out.dtype, device=out.device))
    return out.cpu().numpy() if is_numpy else out


def _aperture(x: torch.Tensor, theta_e, lens_x, lens_y, pixel_scale: float, mask_factor: float):
    """The pixels of images ``x`` ``(..., H, W)`` within ``mask_factor · θ_E`` of the lens
    centre (bool, broadcasting against ``x``); geometry in float64, so that the mask
    does not depend on the image dtype."""
    h, w = x.shape[-2:]
    ax_x = (torch.arange(w, dtype=torch.float64, device=x.device) - (w - 1) / 2) * pixel_scale
    ax_y = (torch.arange(h, dtype=torch.float64, device=x.device) - (h - 1) / 2) * pixel_scale
    lead = x.ndim - 2

    def geom(v):
        # Left-align per-image parameters with the leading axes of the images, so
        # (B,) parameters pair with (B, H, W) and with (B, 1, H, W) images alike.
        t = _as_tensor(v, dtype=torch.float64, device=x.device)
        if 0 < t.ndim < lead:
            t = t.reshape(t.shape + (1,) * (lead - t.ndim))
        return t[..., None, None]

    te, cx, cy = geom(theta_e), geom(lens_x), geom(lens_y)
    r2 = (ax_x - cx) ** 2 + (ax_y[:, None] - cy) ** 2
    return r2 <= (mask_factor * te) ** 2
