"""Whitening statistics: the pixel mean and standard deviation of the training images
(after the input transform of :mod:`subslope.nre.inputs`, which the file records).

Every image (training, validation, test and HST) is whitened with the same two scalars,
``(x − mean) / std``, computed over all pixels of all training shards (docs/physics.md).
:func:`pixel_statistics` streams over the shards in chunks of images and accumulates in
float64; partial results are merged with the parallel form of Welford's algorithm
(Chan, Golub & LeVeque 1979)::

    n = n_a + n_b,  δ = m_b − m_a,
    mean = m_a + δ · n_b / n,  M2 = M2_a + M2_b + δ² · n_a · n_b / n,

so the result does not depend on how the pixels are chunked (up to rounding) and the
two-pass accuracy of each chunk is kept. ``std`` is the population standard deviation
(``ddof = 0``), as ``numpy.std``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from subslope.io.atomic import read_json, write_json
from subslope.io.shards import file_sha256, open_shard

from .inputs import InputTransform, shard_light_models

__all__ = ["Moments", "pixel_statistics", "compute_whitening", "load_whitening"]

WHITENING_FORMAT = "subslope-whitening"


@dataclass(frozen=True)
class Moments:
    """Count, mean and sum of squared deviations (M2) of a set of values."""

    n: int = 0
    mean: float = 0.0
    m2: float = 0.0

    @classmethod
    def of(cls, values: np.ndarray) -> Moments:
        v = np.asarray(values, dtype=np.float64).ravel()
        if v.size == 0:
            return cls()
        mean = float(v.mean())
        return cls(int(v.size), mean, float(np.sum((v - mean) ** 2)))

    def merge(self, other: Moments) -> Moments:
        """Chan et al. parallel combination."""
        if other.n == 0:
            return self
        if self.n == 0:
            return other
        n = self.n + other.n
        delta = other.mean - self.mean
        return Moments(
            n,
            self.mean + delta * other.n / n,
            self.m2 + other.m2 + delta * delta * self.n * other.n / n,
        )

    @property
    def var(self) -> float:
        return self.m2 / self.n if self.n else float("nan")

    @property
    def std(self) -> float:
        return float(np.sqrt(self.var))


def pixel_statistics(
    paths: Sequence[str | os.PathLike[str]],
    *,
    chunk_images: int = 256,
    inputs: InputTransform | None = None,
) -> Moments:
    """Moments of all pixels of the ``images`` of the given shards (read in chunks), after
    the input transform ``inputs`` (:mod:`subslope.nre.inputs`; ``None``: as stored)."""
    if chunk_images < 1:
        raise ValueError(f"chunk_images = {chunk_images!r} must be >= 1")
    inputs = inputs or InputTransform()
    total = Moments()
    for path in paths:
        with open_shard(path) as shard:
            data = shard.images
            for start in range(0, data.shape[0], chunk_images):
                stop = min(start + chunk_images, data.shape[0])
                light = (
                    shard_light_models(path, shard.file, start, stop)
                    if inputs.needs_light
                    else None
                )
                total = total.merge(Moments.of(inputs.apply(data[start:stop], light)))
    return total


def compute_whitening(
    paths: Sequence[str | os.PathLike[str]],
    out_path: str | os.PathLike[str],
    *,
    chunk_images: int = 256,
    inputs: InputTransform | None = None,
) -> dict:
    """Write the whitening JSON of the shards ``paths`` (their pixels after the input
    transform ``inputs``) and return its content.

    Keys: ``format``, ``mean``, ``std``, ``inputs`` (the transform,
    :meth:`~subslope.nre.inputs.InputTransform.to_json`), ``n_pixels``, ``n_images`` and
    ``shards`` (path, SHA-256 and size in bytes of each input, in the given order).
    """
    if not paths:
        raise ValueError("compute_whitening needs at least one shard")
    inputs = inputs or InputTransform()
    m = pixel_statistics(paths, chunk_images=chunk_images, inputs=inputs)
    if not (m.n and np.isfinite(m.mean) and m.std > 0):
        raise ValueError(
            f"degenerate pixel statistics of {list(map(str, paths))}: mean {m.mean}, std {m.std}"
        )
    n_images = 0
    shards = []
    for p in paths:
        with open_shard(p) as s:
            n_images += len(s)
        shards.append({"path": str(p), "sha256": file_sha256(p), "bytes": Path(p).stat().st_size})
    result = {
        "format": WHITENING_FORMAT,
        "mean": m.mean,
        "std": m.std,
        "inputs": inputs.to_json(),
        "n_pixels": m.n,
        "n_images": n_images,
        "shards": shards,
    }
    write_json(Path(out_path), result)
    return result


def load_whitening(path: str | os.PathLike[str]) -> tuple[float, float]:
    """``(mean, std)`` from a whitening JSON file."""
    d = read_json(path)
    if d.get("format") != WHITENING_FORMAT:
        raise ValueError(f"{path} is not a whitening file (format {d.get('format')!r})")
    return float(d["mean"]), float(d["std"])
