"""Pixelated (e.g. COSMOS) surface-brightness maps evaluated at arbitrary positions.

A stamp ``S[j, i]`` (e⁻/s per arcsec², *surface brightness*, not per-pixel flux) lives
on its own grid of pixel size ``Δ_s``: in the stamp frame, pixel ``(j, i)`` sits at
``u_i = (i − (W − 1)/2)·Δ_s``, ``v_j = (j − (H − 1)/2)·Δ_s`` (the project's grid
convention). The stamp is rotated counter-clockwise by ``angle`` (radians, in the
x–y plane with y along the row index) and centred on ``(center_x, center_y)``::

    (u, v) = R(−angle) · (x − center_x, y − center_y).

Interpolation uses :func:`torch.nn.functional.grid_sample` with
``align_corners=False`` (normalised −1/+1 = outer edges of the edge pixels, so pixel
centres map exactly to the convention above) and ``padding_mode='zeros'``:

- ``'bilinear'`` (default): exact for linear functions inside the stamp, non-negative
  for non-negative stamps. Each stamp pixel contributes a tent of integral ``Δ_s²``,
  so the integral of the interpolant is exactly ``Σ S · Δ_s²``: evaluating on a finer,
  unlensed grid and multiplying by the pixel area conserves flux (up to the grid's
  own quadrature error).
- ``'bicubic'``: Keys cubic convolution (a = −0.75), smoother and also flux-conserving
  in the same sense, but it can overshoot (small negative values next to sharp
  features). An accuracy knob.
- ``'nearest'``: for tests/debugging.

Outside the stamp the source is zero: with zero padding the interpolant falls to zero
within one stamp pixel beyond the edge pixel centres (i.e. half a pixel beyond the
stamp edge for bilinear) and is exactly zero further out.

Batching: ``stamps`` of shape ``(B, H, W)``: one source per batch element (stamps of
different sizes are zero-padded with :func:`pad_stamps`); coordinates have leading
dimension ``B`` (or 1) and any trailing shape; parameters broadcast with the
coordinates (e.g. ``(B, 1)`` against ``(B, P)``). A single ``(H, W)`` stamp works with
coordinates of any shape.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["pixelated_light", "pad_stamps", "PixelatedSource"]

_MODES = ("bilinear", "bicubic", "nearest")


def _t(value, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(value, dtype=like.dtype, device=like.device)


def pixelated_light(
    x,
    y,
    stamps: torch.Tensor,
    pixel_scale,
    angle=0.0,
    center_x=0.0,
    center_y=0.0,
    *,
    order: str = "bilinear",
    stamp_offset_x=0.0,
    stamp_offset_y=0.0,
) -> torch.Tensor:
    """Surface brightness (e⁻/s/arcsec²) of pixelated sources at (x, y).

    Parameters
    ----------
    x, y : torch.Tensor
        Positions, arcsec (e.g. ray-traced source-plane positions). Shape ``(B, ...)``
        for batched stamps, any shape for a single stamp.
    stamps : torch.Tensor
        ``(H, W)`` or ``(B, H, W)`` surface brightness maps, e⁻/s per arcsec².
    pixel_scale : float or tensor
        Stamp pixel size Δ_s, arcsec (> 0); broadcasts with x.
    angle : float or tensor
        Counter-clockwise rotation of the source, radians.
    center_x, center_y : float or tensor
        Position of the stamp centre, arcsec.
    order : {'bilinear', 'bicubic', 'nearest'}
        Interpolation order (accuracy knob).
    stamp_offset_x, stamp_offset_y : float or tensor
        Offset (stamp pixels) of the source centre from the array centre, as returned
        by :func:`pad_stamps`.

    Returns
    -------
    torch.Tensor
        Broadcast shape of the coordinates (with the batch dimension ``B``).
    """
    if order not in _MODES:
        raise ValueError(f"order must be one of {_MODES}, got {order!r}")
    x = torch.as_tensor(x)
    if not x.is_floating_point():
        x = x.to(torch.get_default_dtype())
    stamps = torch.as_tensor(stamps).to(dtype=x.dtype, device=x.device)
    if stamps.ndim not in (2, 3):
        raise ValueError(f"stamps must have shape (H, W) or (B, H, W), got {tuple(stamps.shape)}")
    y = _t(y, x)
    pix = _t(pixel_scale, x)
    if not bool((pix > 0).all()):
        raise ValueError(f"pixel_scale must be > 0 arcsec, got {pixel_scale!r}")
    ang = _t(angle, x)
    dx = x - _t(center_x, x)
    dy = y - _t(center_y, x)
    c, s = torch.cos(ang), torch.sin(ang)
    u = c * dx + s * dy
    v = -s * dx + c * dy
    h, w = stamps.shape[-2:]
    ix = u / pix + (w - 1) / 2.0 + _t(stamp_offset_x, x)
    iy = v / pix + (h - 1) / 2.0 + _t(stamp_offset_y, x)
    return _sample(stamps, ix, iy, order)


def _sample(stamps: torch.Tensor, ix: torch.Tensor, iy: torch.Tensor, order: str) -> torch.Tensor:
    """``stamps`` interpolated at the continuous stamp-pixel indices ``(ix, iy)``
    (0 outside the stamp), in the broadcast shape of the indices."""
    h, w = stamps.shape[-2:]
    ix, iy = torch.broadcast_tensors(ix, iy)
    # align_corners=False: index i ↔ normalised (2i + 1)/W − 1.
    gx = (2.0 * ix + 1.0) / w - 1.0
    gy = (2.0 * iy + 1.0) / h - 1.0
    out_shape = gx.shape
    if stamps.ndim == 2:
        inp = stamps[None, None]
        grid = torch.stack([gx.reshape(1, 1, -1), gy.reshape(1, 1, -1)], dim=-1)
    else:
        b = stamps.shape[0]
        if gx.ndim == 0 or gx.shape[0] not in (1, b):
            raise ValueError(
                f"coordinates must have leading batch dimension {b} (or 1) to match stamps "
                f"{tuple(stamps.shape)}, got broadcast shape {tuple(gx.shape)}"
            )
        if gx.shape[0] == 1 and b > 1:
            gx = gx.expand(b, *gx.shape[1:])
            gy = gy.expand(b, *gy.shape[1:])
            out_shape = gx.shape
        inp = stamps[:, None]
        grid = torch.stack([gx.reshape(b, 1, -1), gy.reshape(b, 1, -1)], dim=-1)
    vals = F.grid_sample(inp, grid, mode=order, padding_mode="zeros", align_corners=False)
    return vals.reshape(out_shape)


def pad_stamps(stamps, *, dtype=None, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Zero-pad stamps of different sizes into one ``(B, H_max, W_max)`` tensor.

    Each stamp is centred (extra odd row/column at the end). Returns the padded
    tensor and offsets ``(B, 2)`` = (offset_x, offset_y) in stamp pixels (0 or −0.5):
    pass them as ``stamp_offset_x=offsets[:, 0:1]``, ``stamp_offset_y=offsets[:, 1:2]``
    to :func:`pixelated_light` so each source stays centred on its own centre.
    """
    arrays = [
        torch.as_tensor(np.asarray(s) if not isinstance(s, torch.Tensor) else s) for s in stamps
    ]
    if not arrays:
        raise ValueError("stamps must contain at least one 2-D array")
    for k, a in enumerate(arrays):
        if a.ndim != 2:
            raise ValueError(f"stamps[{k}] must be 2-D, got shape {tuple(a.shape)}")
    dtype = dtype or (
        arrays[0].dtype if arrays[0].is_floating_point() else torch.get_default_dtype()
    )
    hmax = max(a.shape[0] for a in arrays)
    wmax = max(a.shape[1] for a in arrays)
    out = torch.zeros(len(arrays), hmax, wmax, dtype=dtype, device=device)
    offsets = torch.zeros(len(arrays), 2, dtype=dtype, device=device)
    for k, a in enumerate(arrays):
        h, w = a.shape
        top, left = (hmax - h) // 2, (wmax - w) // 2
        out[k, top : top + h, left : left + w] = a.to(dtype=dtype, device=device)
        # centre of the original stamp in padded indices minus the padded centre
        offsets[k, 0] = left + (w - 1) / 2.0 - (wmax - 1) / 2.0
        offsets[k, 1] = top + (h - 1) / 2.0 - (hmax - 1) / 2.0
    return out, offsets


@dataclass
class PixelatedSource:
    """A pixelated source: stamps (e⁻/s/arcsec²) plus placement (see module docstring)."""

    stamps: torch.Tensor
    pixel_scale: torch.Tensor | float
    angle: torch.Tensor | float = 0.0
    center_x: torch.Tensor | float = 0.0
    center_y: torch.Tensor | float = 0.0
    order: str = "bilinear"

    def surface_brightness(self, x, y) -> torch.Tensor:
        """e⁻/s per arcsec² at (x, y) (arcsec)."""
        return pixelated_light(
            x,
            y,
            self.stamps,
            self.pixel_scale,
            self.angle,
            self.center_x,
            self.center_y,
            order=self.order,
        )
