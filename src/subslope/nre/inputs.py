"""What the estimator sees of an image: the input transform before whitening and mask.

``training.inputs`` (recorded in the estimator's metadata, applied alike to training,
validation and test shards, the CDM and null scenes, the HST cutouts and the domain
check), per pixel ``d`` in e⁻/s:

- ``whitened``: ``d`` itself (the reference analysis);
- ``snr``: the per-pixel signal-to-noise ``d / sqrt(σ_bg² + max(d, 0)/t)``, with the
  detector's empty-pixel σ_bg (e⁻/s) and exposure time ``t`` (s): a bright lens core
  (S/N ~ 10³) is compressed as √d, faint arcs (S/N ~ 1–30) are left nearly linear;
- ``light_subtracted``: ``d − m``, with ``m`` the lens-light model fitted to that image
  (:mod:`subslope.physics.light.subtract`; stored with the shard, group ``light_fit``).

Whitening (:mod:`subslope.nre.whitening`) is then measured on the transformed training
images, and the θ_E mask applied last (:func:`subslope.nre.preprocess.preprocess`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass

import h5py
import numpy as np

from subslope.io.shards import LIGHT_FIT_GROUP, CheckedRows
from subslope.physics.light.subtract import STORED, model_images

__all__ = [
    "INPUT_KINDS",
    "InputTransform",
    "ShardLightModels",
    "read_light_fit",
    "shard_light_models",
]

#: The choices of ``training.inputs``.
INPUT_KINDS = ("whitened", "snr", "light_subtracted")


@dataclass(frozen=True)
class InputTransform:
    """One of :data:`INPUT_KINDS` with the detector numbers ``snr`` needs
    (``background_sigma`` e⁻/s per pixel, ``exposure_time`` s)."""

    kind: str = "whitened"
    background_sigma: float = 0.0
    exposure_time: float = 0.0

    def __post_init__(self):
        if self.kind not in INPUT_KINDS:
            raise ValueError(f"training.inputs = {self.kind!r}; allowed: {list(INPUT_KINDS)}")
        if self.kind == "snr" and not (
            math.isfinite(self.background_sigma)
            and self.background_sigma > 0
            and math.isfinite(self.exposure_time)
            and self.exposure_time > 0
        ):
            raise ValueError(
                "inputs 'snr' needs background_sigma > 0 and exposure_time > 0, got "
                f"{self.background_sigma!r} and {self.exposure_time!r}"
            )

    @property
    def needs_light(self) -> bool:
        """Whether :meth:`apply` takes the fitted lens-light model."""
        return self.kind == "light_subtracted"

    def apply(self, images, light=None) -> np.ndarray:
        """Transformed ``images`` ``(..., H, W)`` as float32; ``light``: the fitted model of
        each image (same shape), required by ``light_subtracted`` only."""
        x = np.asarray(images, dtype=np.float32)
        if self.kind == "whitened":
            return x
        if self.kind == "snr":
            var = self.background_sigma**2 + np.maximum(x, 0.0) / self.exposure_time
            return (x / np.sqrt(var)).astype(np.float32)
        if light is None:
            raise ValueError("inputs 'light_subtracted' needs the fitted lens-light model")
        light = np.asarray(light, dtype=np.float32)
        if light.shape != x.shape:
            raise ValueError(f"light model {light.shape} does not match the images {x.shape}")
        return x - light

    def to_json(self) -> dict:
        return {
            "kind": self.kind,
            "background_sigma": float(self.background_sigma),
            "exposure_time": float(self.exposure_time),
        }

    @classmethod
    def from_json(cls, d: Mapping | None) -> InputTransform:
        """The transform of an estimator's metadata (``None``: an estimator trained before
        the choice existed, on whitened pixels)."""
        if d is None:
            return cls()
        return cls(
            str(d["kind"]), float(d.get("background_sigma", 0)), float(d.get("exposure_time", 0))
        )


def read_light_fit(path, fh: h5py.File, lo: int, hi: int) -> dict[str, np.ndarray]:
    """Stored lens-light fit parameters of rows ``lo:hi`` of the open shard ``fh``
    (``path`` names it in errors); a shard without them is refused with the key named."""
    missing = [k for k in STORED if f"{LIGHT_FIT_GROUP}/{k}" not in fh]
    if missing:
        raise ValueError(
            f"shard {path!s} has no lens-light fit ({LIGHT_FIT_GROUP}/{missing[0]} missing): "
            "inputs 'light_subtracted' need shards simulated with simulation.light_fit on "
            "(rerun the shard jobs: snakemake -R simulate_shard)"
        )
    return {k: np.asarray(CheckedRows(path, fh[f"{LIGHT_FIT_GROUP}/{k}"])[lo:hi]) for k in STORED}


def shard_light_models(path, fh: h5py.File, lo: int, hi: int, take=None) -> np.ndarray:
    """The fitted lens-light model images of rows ``lo:hi`` of the open shard ``fh``, or
    of the rows ``lo + take`` only (``take``: indices into ``lo:hi``)."""
    params = read_light_fit(path, fh, lo, hi)
    if take is not None:
        params = {k: v[np.asarray(take)] for k, v in params.items()}
    npix = fh["images"].shape[-1]
    return model_images(params, np.asarray(fh["psf"]), npix, _pixel_scale(fh))


class ShardLightModels:
    """The fitted lens-light models of an open shard, built on slicing (``[lo:hi]``), so
    that a consumer that reads the images in batches reads their models alike."""

    def __init__(self, path, fh: h5py.File):
        read_light_fit(path, fh, 0, 0)
        self.path, self.fh = path, fh

    def __len__(self) -> int:
        return int(self.fh["images"].shape[0])

    def __getitem__(self, rows: slice) -> np.ndarray:
        if not isinstance(rows, slice) or rows.step not in (None, 1):
            raise TypeError("lens-light models are read as contiguous slices [lo:hi]")
        lo, hi, _ = rows.indices(len(self))
        return shard_light_models(self.path, self.fh, lo, max(lo, hi))


def _pixel_scale(fh: h5py.File) -> float:
    """The shard's pixel size (arcsec), from its recorded instrument section."""
    cfg = fh.attrs["config"]
    sections = json.loads(cfg) if isinstance(cfg, (str, bytes)) else cfg
    return float(sections["instrument"]["pixel_scale"])
