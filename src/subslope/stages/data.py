"""Stage ``data``: materialise the checksummed real data under the resources folder
(rule fetch_data; :mod:`subslope.io.resources`)."""

from __future__ import annotations

from subslope.io.resources import fetch_files

__all__ = ["fetch_files"]
