"""The precision at which drawn halo populations are kept, stored and rendered.

A training image at N_sub ≈ 1500 holds ~10⁴ population numbers but only 10⁴ pixels: kept in
float64 they were three quarters of a shard. Each drawn field is therefore rounded, right
after it is drawn, to the dtype it is stored in; everything derived from it (EPL
amplitudes, NFW scale radii, tNFW truncation radii) is computed from the rounded value, and
the renderer sees only rounded values. Reading a shard back and deriving again gives the
same float64 inputs, so a re-render is bit-exact (:mod:`subslope.simulation.rerender`).

The dtypes and what they cost in the physics (IEEE round to nearest):

=========== ========= ===========================================================
field       stored    resolution
=========== ========= ===========================================================
mass, c200  float32   relative 6e-8
x, y        float16   ≤ 0.001 arcsec at |x| < 2 arcsec, 1/50 of an HST pixel
γ_i         float16   ≤ 0.002 (0.001 below γ = 2), kept inside its truncation bounds
e1, e2      float16   ≤ 1.2e-4 at |e| < 0.25
LoS fields  float32   relative 6e-8 (about 16 halos an image: size does not matter)
images      float32   16 of the 23 mantissa bits: relative 7.6e-6 (:func:`rounded_image`)
=========== ========= ===========================================================

These resolutions are far below the widths of the priors the values are drawn from (and,
for the pixels, below their noise), so the rounded populations follow the same
distributions; the image labels (``params/``) stay float64. A training image at N_sub =
1500 + LoS takes ~42 KB in a shard (``benchmarks/simulate_end_to_end.py``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

__all__ = [
    "IMAGE_MANTISSA_BITS",
    "SUBHALO_DTYPES",
    "LOS_DTYPE",
    "rounded",
    "rounded_image",
    "rounded_los",
    "stored",
]

#: Mantissa bits an image pixel keeps of float32's 23 (see :func:`rounded_image`).
IMAGE_MANTISSA_BITS = 16

#: Stored dtype of each drawn subhalo field (derived fields are not stored).
SUBHALO_DTYPES: dict[str, type[np.floating]] = {
    "mass": np.float32,
    "c200": np.float32,
    "x": np.float16,
    "y": np.float16,
    "gamma": np.float16,
    "e1": np.float16,
    "e2": np.float16,
}

#: Stored dtype of every line-of-sight field.
LOS_DTYPE = np.float32


def rounded_image(image: np.ndarray, bits: int = IMAGE_MANTISSA_BITS) -> np.ndarray:
    """float32 ``image`` with each pixel rounded to ``bits`` mantissa bits (round half to
    even on the bit pattern; exact and the same on every machine).

    The rounding error is at most 2^-(bits+1) of the pixel value: 7.6e-6 at 16 bits, which
    is under 1% of the pixel's noise σ wherever its signal-to-noise ratio is below 1300 (an
    F814W pixel of 410 e⁻/s over 2,200 s has about 950). The zeroed low bits make the
    images compress to ~24 KB instead of ~31 KB each (100 × 100 pixels, gzip + shuffle).
    A non-finite pixel (before or after rounding) raises ``ValueError``.
    """
    if not 1 <= bits <= 23:
        raise ValueError(f"bits = {bits!r} must lie in [1, 23]")
    u = np.ascontiguousarray(image, dtype=np.float32).view(np.uint32)
    if bits == 23:
        out = u.view(np.float32).copy()
    else:
        shift = np.uint32(23 - bits)
        bias = np.uint32((1 << (23 - bits - 1)) - 1) + ((u >> shift) & np.uint32(1))
        mask = np.uint32((0xFFFFFFFF << (23 - bits)) & 0xFFFFFFFF)
        out = ((u + bias) & mask).view(np.float32)
    if not np.all(np.isfinite(out)):  # a NaN's payload can round to inf: refuse both
        raise ValueError("image has non-finite pixels (NaN or overflow): not stored")
    return out


def rounded(values, dtype, name: str, bounds: tuple[float, float] | None = None) -> np.ndarray:
    """``values`` rounded to ``dtype`` and returned as float64 (exactly representable).

    ``bounds`` (low, high): a value that rounding carried outside is moved to the nearest
    representable value inside. Raises ``ValueError`` naming ``name`` if a value does not
    fit the dtype (overflow to ±inf) or is not finite.
    """
    v = np.asarray(values, dtype=np.float64)
    with np.errstate(over="ignore"):
        r = v.astype(dtype)
    if not np.all(np.isfinite(r)):
        bad = float(v[~np.isfinite(r)][0])
        raise ValueError(
            f"{name} = {bad!r} cannot be stored as {np.dtype(dtype).name} "
            f"(largest finite value {float(np.finfo(dtype).max):.6g})"
        )
    if bounds is not None:
        low, high = (np.float64(b) for b in bounds)
        lo, hi = np.array([low, high]).astype(dtype)
        if np.float64(lo) < low:  # compared in float64: numpy would compare in ``dtype``
            lo = np.nextafter(lo, dtype(np.inf))
        if np.float64(hi) > high:
            hi = np.nextafter(hi, dtype(-np.inf))
        r = np.clip(r, lo, hi)
    return r.astype(np.float64)


def stored(arrays: Mapping[str, np.ndarray], dtypes) -> dict[str, np.ndarray]:
    """The arrays to write: ``counts`` as int64 and each field of ``dtypes`` (a mapping
    field → dtype, or one dtype for every field) cast to its dtype; fields not named in a
    mapping are derived on reading and left out."""
    out = {"counts": np.asarray(arrays["counts"], dtype=np.int64)}
    for key, value in arrays.items():
        if key == "counts" or value is None:
            continue
        dtype = dtypes.get(key) if isinstance(dtypes, Mapping) else dtypes
        if dtype is not None:
            out[key] = np.asarray(value).astype(dtype)
    return out


def rounded_los(pop):
    """A line-of-sight population (:class:`subslope.simulation.los_halos.LosPopulation`) with
    every field rounded to :data:`LOS_DTYPE` (all of them are stored)."""
    return dataclasses.replace(
        pop,
        **{
            f.name: rounded(getattr(pop, f.name), LOS_DTYPE, f"los.{f.name}")
            for f in dataclasses.fields(pop)
            if f.name not in ("profile", "counts") and getattr(pop, f.name) is not None
        },
    )
