"""Ragged per-system arrays: flat members + counts ↔ offsets ↔ padded ``(B, N)``.

The simulator stores a population (subhalos of each lens, halos of each line-of-sight
slice) as one flat array of all members plus per-system counts; system ``b`` holds
``values[offsets[b]:offsets[b + 1]]``. The renderer works on the padded layout, a
``(B, N)`` array and a boolean mask of the real slots. This module converts between
the two, and concatenates the fields of systems drawn one by one from their own
random generators (:func:`draw_per_system`); it depends on numpy only.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "counts_to_offsets",
    "counts_to_starts",
    "draw_per_system",
    "pack_ragged",
    "unpack_ragged",
]


def _numpy(x) -> np.ndarray:
    """A numpy view of ``x`` (torch tensors are detached and copied to the host)."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def counts_to_offsets(counts: np.ndarray) -> np.ndarray:
    """``(B,)`` counts → ``(B + 1,)`` offsets (``offsets[0] = 0``)."""
    counts = np.asarray(counts)
    if counts.ndim != 1 or (counts.size and counts.min() < 0):
        raise ValueError(f"counts must be a 1-D array of non-negative integers, got {counts!r}")
    return np.concatenate([[0], np.cumsum(counts, dtype=np.int64)])


def counts_to_starts(counts: np.ndarray) -> np.ndarray:
    """``(B,)`` counts → ``(B,)`` index of each system's first member."""
    return counts_to_offsets(counts)[:-1]


def _counts_from(counts: np.ndarray | None, offsets: np.ndarray | None, n_flat: int) -> np.ndarray:
    if (counts is None) == (offsets is None):
        raise ValueError("give exactly one of counts= or offsets=")
    if offsets is not None:
        offsets = np.asarray(offsets, dtype=np.int64)
        if offsets.ndim != 1 or offsets.size < 1 or offsets[0] != 0 or np.any(np.diff(offsets) < 0):
            raise ValueError(f"offsets must be non-decreasing, 1-D and start at 0, got {offsets!r}")
        counts = np.diff(offsets)
    counts = np.asarray(counts, dtype=np.int64)
    if counts.ndim != 1 or (counts.size and counts.min() < 0):
        raise ValueError(f"counts must be 1-D and non-negative, got {counts!r}")
    if counts.sum() != n_flat:
        raise ValueError(
            f"counts/offsets describe {int(counts.sum())} members but values has {n_flat}"
        )
    return counts


def pack_ragged(
    values: np.ndarray,
    *,
    counts: np.ndarray | None = None,
    offsets: np.ndarray | None = None,
    n_max: int | None = None,
    fill: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Flat ragged array → padded ``(B, n_max)`` array and bool mask (vectorised).

    ``values`` is the concatenation of all systems' members (``(M,)``, or ``(M, ...)``
    for vector-valued members); ``counts`` ``(B,)`` or ``offsets`` ``(B + 1,)``.
    ``n_max`` defaults to ``max(counts)``; padded slots hold ``fill``.
    """
    values = np.asarray(values)
    counts = _counts_from(counts, offsets, values.shape[0])
    n_sys = counts.size
    width = int(counts.max()) if n_max is None and n_sys else int(n_max or 0)
    if n_sys and width < counts.max():
        raise ValueError(f"n_max={n_max} is smaller than the largest count {int(counts.max())}")
    mask = np.arange(width)[None, :] < counts[:, None]
    padded = np.full((n_sys, width) + values.shape[1:], fill, dtype=values.dtype)
    padded[mask] = values  # row-major order of the mask == concatenation order
    return padded, mask


def unpack_ragged(padded, mask) -> tuple[np.ndarray, np.ndarray]:
    """Padded ``(B, N, ...)`` + mask (numpy arrays or torch tensors) → flat values
    ``(M, ...)`` and counts ``(B,)``."""
    padded, mask = _numpy(padded), _numpy(mask)
    mask = np.asarray(mask, dtype=bool)
    if padded.shape[:2] != mask.shape:
        raise ValueError(f"padded shape {padded.shape} does not start with mask shape {mask.shape}")
    return padded[mask], mask.sum(axis=1).astype(np.int64)


def draw_per_system(rng, n_systems: int, draw) -> dict[str, np.ndarray]:
    """Fields of ``n_systems`` systems drawn by ``draw(generator, systems)``, where
    ``systems`` is the slice of systems to draw and the result maps field names to flat
    arrays of their members in system order.

    ``rng`` is one ``numpy.random.Generator`` (one call draws every system, field by
    field) or a sequence of ``n_systems`` of them (one call per system, each from its own
    generator, concatenated: a system's draws then do not depend on the others).
    """
    if isinstance(rng, np.random.Generator):
        return draw(rng, slice(0, n_systems))
    rngs = list(rng)
    if len(rngs) != n_systems or not all(isinstance(r, np.random.Generator) for r in rngs):
        raise ValueError(
            f"rng must be a numpy.random.Generator or a sequence of {n_systems} of them "
            f"(one per system), got {len(rngs)} items"
        )
    if not rngs:  # no systems: the empty fields, nothing is drawn from this generator
        return draw(np.random.default_rng(0), slice(0, 0))
    parts = [draw(r, slice(b, b + 1)) for b, r in enumerate(rngs)]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
