"""Ellipticity helpers shared by the elliptical profiles.

Convention (lenstronomy's ``param_util``): with axis ratio ``q`` (minor/major, 0 < q <= 1)
and position angle ``phi`` of the major axis (radian, counter-clockwise from +x),

    e = (1 - q) / (1 + q),   e1 = e cos 2phi,   e2 = e sin 2phi.

The frame of a profile is reached by translating to its centre and rotating by ``phi``:
``x' = cos(phi) dx + sin(phi) dy``, ``y' = -sin(phi) dx + cos(phi) dy`` (lenstronomy
``util.rotate``). All functions are elementwise and broadcast with torch rules.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "ellipticity_to_q_phi",
    "q_phi_to_ellipticity",
    "ellipse_frame",
    "to_frame",
    "from_frame",
]


def _safe_direction(e1: Tensor, e2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Return (e, cos 2phi, sin 2phi) with the direction set to (1, 0) where e = 0.

    The ``where`` on the squared modulus keeps values and gradients finite at e = 0.
    """
    e_sq = e1 * e1 + e2 * e2
    nonzero = e_sq > 0
    e_safe = torch.sqrt(torch.where(nonzero, e_sq, torch.ones_like(e_sq)))
    cos2 = torch.where(nonzero, e1 / e_safe, torch.ones_like(e_sq))
    sin2 = torch.where(nonzero, e2 / e_safe, torch.zeros_like(e_sq))
    e = torch.where(nonzero, e_safe, torch.zeros_like(e_sq))
    return e, cos2, sin2


def _tensors(e1, e2) -> tuple[Tensor, Tensor]:
    if not isinstance(e1, Tensor) and not isinstance(e2, Tensor):
        e1 = torch.as_tensor(e1, dtype=torch.get_default_dtype())
    ref = e1 if isinstance(e1, Tensor) else e2
    e1 = torch.as_tensor(e1, dtype=ref.dtype, device=ref.device)
    e2 = torch.as_tensor(e2, dtype=ref.dtype, device=ref.device)
    return e1, e2


def ellipticity_to_q_phi(e1, e2) -> tuple[Tensor, Tensor]:
    """Axis ratio and position angle from the ellipticity components.

    *Unit*: ``q`` dimensionless, ``phi`` radian in (-pi/2, pi/2] (0 where e1 = e2 = 0).
    q = (1 - e) / (1 + e) with e = sqrt(e1^2 + e2^2); phi = atan2(e2, e1) / 2.
    """
    e1, e2 = _tensors(e1, e2)
    e, cos2, sin2 = _safe_direction(e1, e2)
    return (1 - e) / (1 + e), 0.5 * torch.atan2(sin2, cos2)


def q_phi_to_ellipticity(q, phi) -> tuple[Tensor, Tensor]:
    """Ellipticity components (e1, e2) from axis ratio ``q`` and angle ``phi`` (radian)."""
    q, phi = _tensors(q, phi)
    e = (1 - q) / (1 + q)
    return e * torch.cos(2 * phi), e * torch.sin(2 * phi)


def ellipse_frame(e1, e2) -> tuple[Tensor, Tensor, Tensor]:
    """Axis ratio and the rotation (cos phi, sin phi) of the profile frame.

    Computed without an angle: cos 2phi = e1/e, sin 2phi = e2/e, then the half-angle
    formulas (phi in (-pi/2, pi/2], so cos phi >= 0). Exactly round (e = 0) gives
    q = 1, cos phi = 1, sin phi = 0, with finite gradients.

    Returns ``(q, cos_phi, sin_phi)`` broadcast to the common shape of e1, e2.
    """
    e1, e2 = _tensors(e1, e2)
    e, cos2, sin2 = _safe_direction(e1, e2)
    q = (1 - e) / (1 + e)
    # cos(phi) = sqrt((1 + cos 2phi)/2) >= 1/sqrt(2) when cos 2phi >= 0; otherwise use
    # sin(phi) = sign(sin 2phi) sqrt((1 - cos 2phi)/2) >= 1/sqrt(2) to avoid dividing by ~0.
    big_c = cos2 >= 0
    c_from_c = torch.sqrt(torch.clamp(0.5 * (1 + cos2), min=0.5))
    s_mag = torch.sqrt(torch.clamp(0.5 * (1 - cos2), min=0.5))
    s_from_s = torch.where(sin2 < 0, -s_mag, s_mag)
    cos_phi = torch.where(big_c, c_from_c, 0.5 * sin2 / s_from_s)
    sin_phi = torch.where(big_c, 0.5 * sin2 / c_from_c, s_from_s)
    return q, cos_phi, sin_phi


def to_frame(dx: Tensor, dy: Tensor, cos_phi: Tensor, sin_phi: Tensor) -> tuple[Tensor, Tensor]:
    """Rotate offsets (arcsec) into the profile frame: x' = c dx + s dy, y' = -s dx + c dy."""
    return cos_phi * dx + sin_phi * dy, cos_phi * dy - sin_phi * dx


def from_frame(ax: Tensor, ay: Tensor, cos_phi: Tensor, sin_phi: Tensor) -> tuple[Tensor, Tensor]:
    """Rotate a vector from the profile frame back to the sky frame (inverse of ``to_frame``)."""
    return cos_phi * ax - sin_phi * ay, sin_phi * ax + cos_phi * ay
