"""Stage ``gallery``: the figure of the real HST cutouts (rule plot_hst_gallery)."""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence

from subslope.figures.gallery import plot_hst_gallery
from subslope.io.observations import load_hst

__all__ = ["plot_gallery"]

log = logging.getLogger(__name__)


def plot_gallery(
    folder: str | os.PathLike[str],
    outputs: Sequence[str | os.PathLike[str]],
    *,
    run_name: str,
    pixel_scale: float,
) -> None:
    """Load the HST cutouts of ``folder`` and draw them side by side into ``outputs``."""
    observations = load_hst(folder)
    log.info("loaded %d cutouts: %s", len(observations), [o.name for o in observations])
    plot_hst_gallery(observations, list(outputs), run_name=run_name, pixel_scale=pixel_scale)
