"""Counts of the render steps evaluated, for tests and benchmarks.

Every step the renderer evaluates (one count per sub-batch that ran it) increments
:data:`STEP_COUNTS`: ``main_lens``, ``shear``, ``multipoles``, ``subhalos`` (population
pass incl. its sheet), ``los`` (one per line-of-sight plane copy), ``split`` (a
population summed by the near/far split), ``split_rough_tiles`` (tiles of a split
pass that get the exact far field), ``multi_plane``, ``single_plane``, ``lens_light``,
``source_sersic``,
``source_multi_sersic`` (plus ``source_component``, one per multi-Sérsic component
evaluated), ``source_pixelated``, ``supersample_bin``, ``psf``. A component that a
scene does not need is never evaluated, so its count stays 0.
"""

from __future__ import annotations

from collections import Counter

__all__ = ["STEP_COUNTS", "count_step", "reset_step_counts"]

#: Steps evaluated since the last :func:`reset_step_counts`.
STEP_COUNTS: Counter = Counter()


def count_step(name: str, n: int = 1) -> None:
    """Add ``n`` evaluations of step ``name``."""
    STEP_COUNTS[name] += n


def reset_step_counts() -> None:
    """Clear :data:`STEP_COUNTS`."""
    STEP_COUNTS.clear()
