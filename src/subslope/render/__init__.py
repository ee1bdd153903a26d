"""The batched renderer: :func:`render` and :func:`render_smooth` with their
:class:`RenderSettings`.

``settings`` (every knob), ``pipeline`` (one function per step of an image),
``populations`` (population passes and their sheets), ``kernels`` (compiled pair
kernels), ``nearfar`` (the near/far split of large populations, with its measured
error constants in ``split_constants.json``), ``counters`` (steps evaluated).
"""

from subslope.render.pipeline import render, render_smooth
from subslope.render.settings import PixelatedSources, RenderSettings

__all__ = ["PixelatedSources", "RenderSettings", "render", "render_smooth"]
