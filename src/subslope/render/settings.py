"""The renderer's settings: every accuracy and speed knob, and the pixelated sources.

Every field of :class:`RenderSettings` is also the config key
``simulation.render.<field>`` of the same name (the schema gives its range and default;
``docs/performance.md`` its error against run time).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from subslope.config import schema_defaults

__all__ = [
    "RenderSettings",
    "PixelatedSources",
    "chunk_width",
    "INSTRUMENT_FIELDS",
    "NOT_RENDER_KEYS",
]

_RENDER = schema_defaults("simulation.render")
_INSTRUMENT = schema_defaults("instrument")
#: Fields of :class:`RenderSettings` that come from the ``instrument`` section.
INSTRUMENT_FIELDS = ("npix", "pixel_scale", "zero_point")
#: Keys of ``simulation.render`` that are not render settings (they steer the shard job).
NOT_RENDER_KEYS = ("compile_cache",)


@dataclass(frozen=True)
class RenderSettings:
    """Knobs of the renderer (errors and run times of each in ``docs/performance.md``).

    npix, pixel_scale : image size (pixels) and pixel size (arcsec).
    supersample : sub-pixels per pixel side k (surface brightness averaged over k×k).
    dtype, device : torch dtype; device None or 'auto' → 'cuda' if available else 'cpu'
        (at call time).
    n_terms : hypergeometric-series terms of the subhalo / LoS EPL deflections.
    n_terms_main : series terms of the main-lens EPL.
    max_elements : memory budget: members × points of one kernel call (a (b, N, P)
        intermediate in eager mode); sets the sub-batch size off-CPU and the auto
        chunk width.
    chunk_members : members per direct kernel call (rounded down to a power of two);
        None → :func:`chunk_width` (from ``max_elements`` and P only, never from B).
    population : 'auto' | 'split' | 'direct': how a population's deflection is summed.
        'direct' evaluates every member at every point; 'split' uses the near/far
        split of :mod:`subslope.render.nearfar` (exact near field within each member's radius
        r_c, far field interpolated from a node mesh); 'auto' = 'split' for
        populations of at least ``split_min_members`` members on a plane, else 'direct'.
    split_spacing : node spacing h of the far-field mesh, in pixels.
    split_order : Lagrange interpolation points per axis of the far field (4, 6, 8).
    split_tolerance : far-field interpolation error allowed per member (arcsec) in a
        population of ≤ 1000 members, ∝ 1/N above; sets each member's r_c
        (:func:`subslope.render.nearfar.member_rungs`).
    split_min_members : smallest population that 'auto' splits.
    source_interpolation : 'bilinear' | 'bicubic' | 'nearest' for pixelated sources.
    convolution : 'auto' | 'direct' | 'fft' (:func:`subslope.physics.instrument.convolve`).
    zero_point : AB magnitude of 1 e⁻/s.
    compile : 'auto' (torch.compile the EPL chunk kernel on CPU when a C compiler is
        found, eager on failure), 'on' (same, also off-CPU), 'off' (eager).
    batch_images : images rendered together by batching 'auto' (and images per batch
        of a shard job): every per-image step works on the batch.
    batching : 'auto' (batches of ``batch_images`` images on every device), 'per_image'
        (one image at a time) or 'sub_batch' (batches sized from ``max_elements``). An
        image rendered alone and in a batch agree to float rounding, not bit for bit:
        element-wise float32 kernels take a vectorised or a scalar path depending on
        where an element falls in the tensor.
    """

    npix: int = _INSTRUMENT["npix"]
    pixel_scale: float = _INSTRUMENT["pixel_scale"]
    supersample: int = _RENDER["supersample"]
    dtype: torch.dtype = getattr(torch, _RENDER["dtype"])
    device: str | None = None
    n_terms: int = _RENDER["n_terms"]
    n_terms_main: int = _RENDER["n_terms_main"]
    max_elements: int = _RENDER["max_elements"]
    source_interpolation: str = _RENDER["source_interpolation"]
    convolution: str = _RENDER["convolution"]
    zero_point: float = _INSTRUMENT["zero_point"]
    chunk_members: int | None = _RENDER["chunk_members"]
    compile: str = _RENDER["compile"]
    population: str = _RENDER["population"]
    split_spacing: int = _RENDER["split_spacing"]
    split_order: int = _RENDER["split_order"]
    split_tolerance: float = _RENDER["split_tolerance"]
    split_min_members: int = _RENDER["split_min_members"]
    batching: str = _RENDER["batching"]
    batch_images: int = _RENDER["batch_images"]

    @classmethod
    def from_config(
        cls, render: Mapping[str, Any], instrument: Mapping[str, Any], **overrides: Any
    ) -> RenderSettings:
        """The settings of a validated config: ``simulation.render`` (every key but
        :data:`NOT_RENDER_KEYS`) and the instrument's ``npix``, ``pixel_scale`` and
        ``zero_point``; ``device`` 'auto' becomes None (chosen at render time)."""
        values = {k: v for k, v in render.items() if k not in NOT_RENDER_KEYS}
        values.update({k: instrument[k] for k in INSTRUMENT_FIELDS})
        values["dtype"] = getattr(torch, values["dtype"])
        values["device"] = None if values.get("device") in (None, "auto") else values["device"]
        values.update(overrides)
        unknown = sorted(set(values) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise ValueError(f"simulation.render keys {unknown} are not RenderSettings fields")
        return cls(**values)

    def __post_init__(self) -> None:
        for name in (
            "npix",
            "supersample",
            "n_terms",
            "n_terms_main",
            "max_elements",
            "batch_images",
        ):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"RenderSettings.{name} must be a positive int, got {v!r}")
        if not self.pixel_scale > 0:
            raise ValueError(
                f"RenderSettings.pixel_scale must be > 0 arcsec, got {self.pixel_scale!r}"
            )
        if self.chunk_members is not None and (
            not isinstance(self.chunk_members, int) or self.chunk_members < 1
        ):
            raise ValueError(
                "RenderSettings.chunk_members must be None or an int >= 1, got "
                f"{self.chunk_members!r}"
            )
        if self.compile not in ("auto", "on", "off"):
            raise ValueError(
                f"RenderSettings.compile must be 'auto', 'on' or 'off', got {self.compile!r}"
            )
        if self.source_interpolation not in ("bilinear", "bicubic", "nearest"):
            raise ValueError(
                "RenderSettings.source_interpolation must be 'bilinear', 'bicubic' or "
                f"'nearest', got {self.source_interpolation!r}"
            )
        if self.convolution not in ("auto", "direct", "fft"):
            raise ValueError(
                "RenderSettings.convolution must be 'auto', 'direct' or 'fft', got "
                f"{self.convolution!r}"
            )
        if self.population not in ("auto", "split", "direct"):
            raise ValueError(
                "RenderSettings.population must be 'auto', 'split' or 'direct', got "
                f"{self.population!r}"
            )
        if not (isinstance(self.split_tolerance, (int, float)) and self.split_tolerance > 0):
            raise ValueError(
                f"RenderSettings.split_tolerance must be > 0 arcsec, got {self.split_tolerance!r}"
            )
        if self.split_order not in (4, 6, 8):
            raise ValueError(
                f"RenderSettings.split_order must be 4, 6 or 8, got {self.split_order!r}"
            )
        for name, lo, hi in (("split_spacing", 1, 64), ("split_min_members", 1, 1 << 30)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"RenderSettings.{name} must be an int in [{lo}, {hi}], got {v!r}")
        if self.batching not in ("auto", "per_image", "sub_batch"):
            raise ValueError(
                "RenderSettings.batching must be 'auto', 'per_image' or 'sub_batch', got "
                f"{self.batching!r}"
            )
        if not self.dtype.is_floating_point:
            raise ValueError(f"RenderSettings.dtype must be a floating dtype, got {self.dtype}")


@dataclass
class PixelatedSources:
    """Pixelated sources of a batch (see :func:`subslope.physics.light.pixelated.pad_stamps`).

    stamps : (B, H, W) surface brightness at z_source, e⁻/s per arcsec².
    pixel_scale : (B,) stamp pixel size at z_source, arcsec.
    offsets : (B, 2) (offset_x, offset_y) in stamp pixels from ``pad_stamps``.
    """

    stamps: np.ndarray | Tensor
    pixel_scale: np.ndarray
    offsets: np.ndarray | Tensor


def _pow2_floor(n: int) -> int:
    return 1 << (max(1, int(n)).bit_length() - 1)


def chunk_width(settings: RenderSettings, n_points: int, compiled: bool = True) -> int:
    """Members per direct kernel call: ``chunk_members``, or the largest power of two
    ≤ ``max_elements / P`` (compiled kernels: no (N, P) intermediate is stored) or
    ≤ ``max_elements / (32·P)`` (eager: about 32 live intermediates), clamped to
    [1, 4096]. A function of the settings and the number of points only (batch
    invariance)."""
    if settings.chunk_members is not None:
        return _pow2_floor(settings.chunk_members)
    per = max(1, n_points) * (1 if compiled else 32)
    return max(1, min(4096, _pow2_floor(settings.max_elements // per)))
