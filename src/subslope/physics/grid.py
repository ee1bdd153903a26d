"""Pixel grids and supersampling helpers.

Convention (docs/design.md): an ``n``-pixel axis of pixel size ``Δ`` has pixel
centres ``x_i = (i - (n - 1)/2)·Δ`` (arcsec), origin at the image centre, and
``image[j, i]`` sits at ``(x_i, y_j)`` (row index ↔ y, column index ↔ x).

A grid supersampled by ``k`` is the same formula with ``n·k`` points of size ``Δ/k``:
the ``k × k`` sub-pixel centres of each pixel are symmetric about the pixel centre,
so averaging ``k × k`` blocks (:func:`bin_supersampled`) gives back pixel-centre
values exactly for linear functions, and the midpoint-rule pixel average otherwise.
"""

from __future__ import annotations

import torch

from subslope.physics.instrument import PIXEL_SCALE

__all__ = ["axis_coordinates", "pixel_grid", "bin_supersampled"]


def _check_positive_int(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return value


def axis_coordinates(
    npix: int = 100,
    pixel_scale: float = PIXEL_SCALE,
    supersample: int = 1,
    *,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """1-D pixel (or sub-pixel) centres of one axis, arcsec, shape ``(npix·supersample,)``."""
    npix = _check_positive_int("npix", npix)
    k = _check_positive_int("supersample", supersample)
    if not pixel_scale > 0:
        raise ValueError(f"pixel_scale must be > 0 arcsec, got {pixel_scale!r}")
    m = npix * k
    idx = torch.arange(m, dtype=dtype or torch.get_default_dtype(), device=device)
    return (idx - (m - 1) / 2.0) * (pixel_scale / k)


def pixel_grid(
    npix: int = 100,
    pixel_scale: float = PIXEL_SCALE,
    supersample: int = 1,
    *,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Square pixel-centred grid.

    Parameters
    ----------
    npix : int
        Pixels per side of the (unsupersampled) image.
    pixel_scale : float
        Pixel size, arcsec. *Unit: arcsec*
    supersample : int
        Sub-pixels per pixel side ``k`` (accuracy knob for pixel integration).
    dtype, device
        Torch dtype / device (default dtype: ``torch.get_default_dtype()``).

    Returns
    -------
    x, y : torch.Tensor
        Each of shape ``(npix·k, npix·k)``, arcsec; ``x[j, i] = x_i``, ``y[j, i] = y_j``.
    """
    ax = axis_coordinates(npix, pixel_scale, supersample, dtype=dtype, device=device)
    y, x = torch.meshgrid(ax, ax, indexing="ij")
    return x, y


def bin_supersampled(img: torch.Tensor, k: int) -> torch.Tensor:
    """Mean over ``k × k`` blocks of the last two axes (batched over leading axes).

    ``img`` of shape ``(..., H·k, W·k)`` → ``(..., H, W)``. Use on surface brightness
    or on per-sub-pixel values to get the pixel average; multiply by the pixel area to
    turn an averaged surface brightness into a pixel flux.
    """
    k = _check_positive_int("k", k)
    if img.ndim < 2:
        raise ValueError(f"img must have at least 2 dimensions, got shape {tuple(img.shape)}")
    h, w = img.shape[-2:]
    if h % k or w % k:
        raise ValueError(f"img last two dimensions {(h, w)} must be divisible by k={k}")
    if k == 1:
        return img
    blocks = img.reshape(*img.shape[:-2], h // k, k, w // k, k)
    return blocks.mean(dim=(-3, -1))
