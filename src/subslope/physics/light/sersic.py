"""Elliptical Sérsic surface brightness (lenstronomy ``SERSIC_ELLIPSE`` convention).

Profile (Sérsic 1963; the ``b_n`` approximation of lenstronomy's ``SersicUtil.b_n``)::

    I(R) = I_0 · exp(−b_n · ((R / R_s)^(1/n) − 1)),      b_n = 1.9992·n − 0.3271,

with ``I_0`` the surface brightness at ``R = R_s`` (lenstronomy's ``amp``), in
e⁻/s per arcsec². The elliptical radius is the product-average one,
``R² = q·x'² + y'²/q`` in the frame rotated by the position angle φ, where
``e = (1 − q)/(1 + q)``, ``e1 = e·cos 2φ``, ``e2 = e·sin 2φ``. Written directly in e1, e2
(no angle needed, smooth at e = 0)::

    R² = [x²(1 − 2e1 + e²) + y²(1 + 2e1 + e²) − 4·e2·x·y] / (1 − e²),   e² = e1² + e2².

The map (x, y) → (√q x', y'/√q) has unit Jacobian, so the total flux does not depend
on q::

    F = I_0 · 2π n R_s² e^{b_n} Γ(2n) / b_n^{2n}.

This is exact for the profile as defined; only the statement "R_s is the half-light
radius" inherits the error of the b_n approximation (see docs). All normalisations
are done in log space, so n from 0.5 to 8 is stable in float32 as well.

Regularisation: ``R`` is floored at ``r_floor`` (default 1e-4″, the same smoothing as
lenstronomy's ``SersicUtil``) so values and gradients are finite at the centre; set
``r_floor=0`` for the unsmoothed profile (still finite, gradients w.r.t. x, y at the
exact centre are then undefined). lenstronomy's ``max_R_frac`` cut (zero beyond
1000·R_s) is not applied.

Magnitudes: F [e⁻/s] = 10^(−0.4 (mag − zp)), zp = 25.127 (HST F814W AB).
Surface brightness × pixel area (arcsec²) gives e⁻/s per pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from subslope.physics.instrument import ZERO_POINT

__all__ = [
    "ZERO_POINT_F814W",
    "sersic_b_n",
    "sersic_log_flux_per_amp",
    "sersic_total_flux",
    "sersic_amp_from_flux",
    "magnitude_to_flux",
    "flux_to_magnitude",
    "elliptical_radius_squared",
    "sersic_ellipse",
    "sersic_ellipse_from_magnitude",
    "multi_sersic_from_magnitude",
    "SersicEllipse",
    "e1e2_to_q_phi",
]

ZERO_POINT_F814W = ZERO_POINT
_LN10 = math.log(10.0)


def _as_tensor(value, like: torch.Tensor | None = None) -> torch.Tensor:
    """Tensor on ``like``'s dtype/device (floats: default dtype when ``like`` is None)."""
    if like is not None:
        return torch.as_tensor(value, dtype=like.dtype, device=like.device)
    if isinstance(value, torch.Tensor):
        return value if value.is_floating_point() else value.to(torch.get_default_dtype())
    return torch.as_tensor(value, dtype=torch.get_default_dtype())


def e1e2_to_q_phi(e1: torch.Tensor, e2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """lenstronomy ``ellipticity2phi_q``: φ = atan2(e2, e1)/2, q = (1 − e)/(1 + e)."""
    e = torch.sqrt(e1 * e1 + e2 * e2).clamp(max=0.9999)
    return (1.0 - e) / (1.0 + e), 0.5 * torch.atan2(e2, e1)


def sersic_b_n(n_sersic) -> torch.Tensor:
    """lenstronomy's ``b_n ≈ 1.9992 n − 0.3271`` (floored at 1e-5). Dimensionless."""
    n = _as_tensor(n_sersic)
    return (1.9992 * n - 0.3271).clamp(min=1e-5)


def sersic_log_flux_per_amp(r_sersic, n_sersic) -> torch.Tensor:
    """ln(F / I_0) = ln(2π n R_s² e^{b_n} Γ(2n) / b_n^{2n}); R_s in arcsec → ln arcsec²."""
    n = _as_tensor(n_sersic)
    r = _as_tensor(r_sersic, n)
    b = sersic_b_n(n)
    return (
        math.log(2.0 * math.pi)
        + torch.log(n)
        + 2.0 * torch.log(r)
        + b
        + torch.lgamma(2.0 * n)
        - 2.0 * n * torch.log(b)
    )


def sersic_total_flux(amp, r_sersic, n_sersic) -> torch.Tensor:
    """Total flux (e⁻/s) of a Sérsic with ``amp`` = I(R_s) in e⁻/s/arcsec²."""
    a = _as_tensor(amp)
    return a * torch.exp(sersic_log_flux_per_amp(_as_tensor(r_sersic, a), _as_tensor(n_sersic, a)))


def sersic_amp_from_flux(flux, r_sersic, n_sersic) -> torch.Tensor:
    """I(R_s) in e⁻/s/arcsec² giving a total ``flux`` (e⁻/s)."""
    f = _as_tensor(flux)
    return f * torch.exp(-sersic_log_flux_per_amp(_as_tensor(r_sersic, f), _as_tensor(n_sersic, f)))


def magnitude_to_flux(magnitude, zero_point: float = ZERO_POINT_F814W) -> torch.Tensor:
    """Apparent magnitude → flux in e⁻/s: 10^(−0.4 (mag − zp))."""
    m = _as_tensor(magnitude)
    return torch.exp(-0.4 * _LN10 * (m - zero_point))


def flux_to_magnitude(flux, zero_point: float = ZERO_POINT_F814W) -> torch.Tensor:
    """Flux in e⁻/s → apparent magnitude (flux must be > 0)."""
    f = _as_tensor(flux)
    return zero_point - 2.5 * torch.log10(f)


def elliptical_radius_squared(x, y, e1, e2, center_x=0.0, center_y=0.0) -> torch.Tensor:
    """Product-average elliptical radius² ``q x'² + y'²/q`` (arcsec²), written in e1, e2.

    Valid for e = √(e1² + e2²) < 1 (1 − e² is floored at 1e-6 as in lenstronomy);
    the result is clamped at 0 so that it never goes negative.
    """
    x = _as_tensor(x)
    y = _as_tensor(y, x)
    e1 = _as_tensor(e1, x)
    e2 = _as_tensor(e2, x)
    dx = x - _as_tensor(center_x, x)
    dy = y - _as_tensor(center_y, x)
    esq = e1 * e1 + e2 * e2
    norm = (1.0 - esq).abs().clamp(min=1e-6)
    r2 = (
        dx * dx * (1.0 - 2.0 * e1 + esq) + dy * dy * (1.0 + 2.0 * e1 + esq) - 4.0 * e2 * dx * dy
    ) / norm
    return r2.clamp(min=0.0)


def _sersic_log_shape(x, y, r_sersic, n_sersic, e1, e2, center_x, center_y, r_floor):
    """−b_n((R/R_s)^(1/n) − 1) and the converted parameters."""
    if r_floor < 0:
        raise ValueError(f"r_floor must be >= 0 arcsec, got {r_floor!r}")
    r2 = elliptical_radius_squared(x, y, e1, e2, center_x, center_y)
    n = _as_tensor(n_sersic, r2)
    rs = _as_tensor(r_sersic, r2)
    b = sersic_b_n(n)
    if r_floor > 0:
        r2 = r2.clamp(min=r_floor * r_floor)
    # (R/R_s)^(1/n) = exp((ln R² − 2 ln R_s) / (2n)); ln 0 = −inf → 0 (finite) at R = 0.
    t = torch.exp((torch.log(r2) - 2.0 * torch.log(rs)) / (2.0 * n))
    return -b * (t - 1.0), rs, n


def sersic_ellipse(
    x, y, amp, r_sersic, n_sersic, e1, e2, center_x=0.0, center_y=0.0, *, r_floor: float = 1e-4
) -> torch.Tensor:
    """Elliptical Sérsic surface brightness, e⁻/s per arcsec².

    Parameters (all broadcast together, dtype/device follow ``x``)
    ----------
    x, y : arcsec
    amp : surface brightness at R = R_s, e⁻/s/arcsec² (lenstronomy ``amp``)
    r_sersic : R_s (product-average half-light radius), arcsec, > 0
    n_sersic : Sérsic index (tested 0.5 … 8)
    e1, e2 : ellipticity components (e < 1)
    center_x, center_y : arcsec
    r_floor : R is floored at this radius (arcsec), see module docstring
    """
    log_shape, _, _ = _sersic_log_shape(
        x, y, r_sersic, n_sersic, e1, e2, center_x, center_y, r_floor
    )
    return _as_tensor(amp, log_shape) * torch.exp(log_shape)


def sersic_ellipse_from_magnitude(
    x,
    y,
    magnitude,
    r_sersic,
    n_sersic,
    e1,
    e2,
    center_x=0.0,
    center_y=0.0,
    *,
    zero_point: float = ZERO_POINT_F814W,
    r_floor: float = 1e-4,
) -> torch.Tensor:
    """As :func:`sersic_ellipse` with the amplitude set by an apparent magnitude.

    Computed as one exponential, exp(ln F − ln(F/I_0) − b_n(...)), so no intermediate
    overflows for large n.
    """
    log_shape, rs, n = _sersic_log_shape(
        x, y, r_sersic, n_sersic, e1, e2, center_x, center_y, r_floor
    )
    mag = _as_tensor(magnitude, log_shape)
    log_flux = -0.4 * _LN10 * (mag - zero_point)
    return torch.exp(log_flux - sersic_log_flux_per_amp(rs, n) + log_shape)


def multi_sersic_from_magnitude(
    x,
    y,
    magnitude,
    fractions,
    r_sersic,
    n_sersic,
    e1,
    e2,
    center_x,
    center_y,
    *,
    zero_point: float = ZERO_POINT_F814W,
    r_floor: float = 1e-4,
) -> torch.Tensor:
    """Sum of elliptical Sérsic components sharing one total magnitude, e⁻/s per arcsec².

    ``magnitude`` is the total apparent magnitude; component ``k`` carries the flux
    fraction ``fractions[k]`` (≥ 0; the fractions of a system should sum to 1) and the
    shape ``r_sersic[k]`` (arcsec), ``n_sersic[k]``, ``e1[k]``, ``e2[k]`` and centre
    ``center_x[k]``, ``center_y[k]`` (arcsec). Every argument after ``magnitude`` is a
    sequence of length K of values that broadcast like :func:`sersic_ellipse_from_magnitude`'s.
    A component whose fractions are all ≤ 0 is skipped (not evaluated); a zero fraction of
    one system among others adds exact zeros, so the sum does not depend on the batch.
    Components are added in order k = 0, 1, … (a fixed order: deterministic).
    """
    k = len(fractions)
    for name, seq in (
        ("r_sersic", r_sersic),
        ("n_sersic", n_sersic),
        ("e1", e1),
        ("e2", e2),
        ("center_x", center_x),
        ("center_y", center_y),
    ):
        if len(seq) != k:
            raise ValueError(
                f"multi_sersic_from_magnitude: {name} has {len(seq)} components, fractions has {k}"
            )
    out = None
    for j in range(k):
        f = _as_tensor(fractions[j], x if isinstance(x, torch.Tensor) else None)
        if not bool((f > 0).any()):
            continue
        sb = f.clamp(min=0.0) * sersic_ellipse_from_magnitude(
            x,
            y,
            magnitude,
            r_sersic[j],
            n_sersic[j],
            e1[j],
            e2[j],
            center_x[j],
            center_y[j],
            zero_point=zero_point,
            r_floor=r_floor,
        )
        out = sb if out is None else out + sb
    if out is None:
        xt = _as_tensor(x)
        return torch.zeros_like(xt + _as_tensor(y, xt))
    return out


@dataclass
class SersicEllipse:
    """Bundle of Sérsic parameters (tensors or floats; broadcast like the functions).

    ``magnitude`` apparent mag (zero point ``zero_point``); ``r_sersic`` arcsec;
    ``center_x``, ``center_y`` arcsec.
    """

    magnitude: torch.Tensor | float
    r_sersic: torch.Tensor | float
    n_sersic: torch.Tensor | float
    e1: torch.Tensor | float = 0.0
    e2: torch.Tensor | float = 0.0
    center_x: torch.Tensor | float = 0.0
    center_y: torch.Tensor | float = 0.0
    zero_point: float = ZERO_POINT_F814W

    def __post_init__(self) -> None:
        r = torch.as_tensor(self.r_sersic)
        if not bool((r > 0).all()):
            raise ValueError(f"r_sersic must be > 0 arcsec, got {self.r_sersic!r}")
        n = torch.as_tensor(self.n_sersic)
        if not bool((n > 0).all()):
            raise ValueError(f"n_sersic must be > 0, got {self.n_sersic!r}")

    @property
    def flux(self) -> torch.Tensor:
        """Total flux, e⁻/s."""
        return magnitude_to_flux(self.magnitude, self.zero_point)

    @property
    def amp(self) -> torch.Tensor:
        """I(R_s), e⁻/s per arcsec²."""
        return sersic_amp_from_flux(self.flux, self.r_sersic, self.n_sersic)

    def surface_brightness(self, x, y, *, r_floor: float = 1e-4) -> torch.Tensor:
        """e⁻/s per arcsec² at (x, y) (arcsec)."""
        return sersic_ellipse_from_magnitude(
            x,
            y,
            self.magnitude,
            self.r_sersic,
            self.n_sersic,
            self.e1,
            self.e2,
            self.center_x,
            self.center_y,
            zero_point=self.zero_point,
            r_floor=r_floor,
        )
