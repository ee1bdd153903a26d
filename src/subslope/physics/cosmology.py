r"""Cosmological distances and lens-plane unit conversions (numpy, float64).

Every function takes a ``cosmo`` argument (an :mod:`astropy.cosmology` instance,
default :data:`astropy.cosmology.Planck18`). Results are numpy float64 (scalars stay
0-d arrays / floats); redshifts and masses broadcast with numpy rules. Distances of
scalar redshifts are cached per (cosmology, redshifts).

Units (see ``docs/design.md``): distances in physical **Mpc**, masses in **M_sun**,
angles in **arcsec**. Densities "per arcsec" use the lens-plane arcsecond as length
unit, 1 arcsec = ``arcsec_to_mpc(z)`` physical Mpc at the plane's redshift, so that a
mass divided by ``sigma_crit`` (M_sun / arcsec^2) and ``rho_crit`` (M_sun / arcsec^3)
combine directly with angular profile parameters.

Mass -> lens-parameter conversions:

* EPL (docs/simulation.md): :func:`epl_amp_from_m200` returns the amplitude
  :math:`A = \theta_E^{\gamma-1}`, computed in log space so that gamma -> 1 stays
  finite while theta_E itself underflows.
* NFW (lenstronomy ``LensCosmo.nfw_physical2angle`` convention):
  :func:`nfw_params_from_m200_c` returns ``(R_s, alpha_Rs)`` in arcsec and
  :func:`m200_c_from_nfw_params` inverts it.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
from astropy import constants as const
from astropy import units as u
from astropy.cosmology import Planck18
from scipy.special import gammaln

__all__ = [
    "ARCSEC_RAD",
    "NFW_G1",
    "angular_diameter_distance",
    "angular_diameter_distance_z1z2",
    "lens_distances",
    "arcsec_to_mpc",
    "sigma_crit",
    "rho_crit",
    "r200_arcsec",
    "plane_logs",
    "epl_log_amp_from_m200",
    "epl_log_amp_from_logs",
    "epl_amp_from_m200",
    "nfw_params_from_m200_c",
    "m200_c_from_nfw_params",
]

#: One arcsecond in radians.
ARCSEC_RAD = math.pi / (180.0 * 3600.0)
#: NFW g(1) = 1 + ln(1/2): alpha_Rs = 4 rho0 R_s^2 g(1) / Sigma_crit (lenstronomy convention).
NFW_G1 = 1.0 + math.log(0.5)
#: c^2 / (4 pi G) in M_sun / Mpc.
_C2_4PIG = float((const.c**2 / (4.0 * np.pi * const.G)).to_value(u.M_sun / u.Mpc))


def _default(cosmo):
    return Planck18 if cosmo is None else cosmo


def _check_z(name: str, z, allow_zero: bool = False) -> np.ndarray:
    z = np.asarray(z, dtype=np.float64)
    if z.ndim == 0:  # the common case, checked without array reductions
        v = float(z)
        if math.isfinite(v) and (v >= 0.0 if allow_zero else v > 0.0):
            return z
    bad = ~np.isfinite(z) | ((z < 0) if allow_zero else (z <= 0))
    if np.any(bad):
        allowed = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be finite and {allowed}; got {z[bad].ravel()[:3]}")
    return z


def _check_positive(name: str, value) -> np.ndarray:
    value = np.asarray(value, dtype=np.float64)
    bad = ~np.isfinite(value) | (value <= 0)
    if np.any(bad):
        raise ValueError(f"{name} must be finite and > 0; got {value[bad].ravel()[:3]}")
    return value


class _CosmoKey:
    """Hashable wrapper: astropy cosmologies compare by value but are not hashable."""

    __slots__ = ("cosmo", "_key")

    def __init__(self, cosmo):
        self.cosmo = cosmo
        self._key = (type(cosmo).__name__, cosmo.name, repr(cosmo))

    def __hash__(self):
        return hash(self._key)

    def __eq__(self, other):
        return isinstance(other, _CosmoKey) and self._key == other._key


#: The key of each cosmology object seen, by identity (astropy cosmologies are immutable;
#: the object is kept, so its id is never reused): ``repr`` of a cosmology costs ~0.25 ms,
#: more than the distance it keys.
_KEYS: dict[int, tuple[Any, _CosmoKey]] = {}


def _cosmo_key(cosmo) -> _CosmoKey:
    entry = _KEYS.get(id(cosmo))
    if entry is None or entry[0] is not cosmo:
        entry = _KEYS[id(cosmo)] = (cosmo, _CosmoKey(cosmo))
    return entry[1]


def _da12(cosmo, z1, z2):
    # astropy >= 7 takes (z1, z2); older versions only have ``*_z1z2``.
    try:
        d = cosmo.angular_diameter_distance(z1, z2)
    except TypeError:
        d = cosmo.angular_diameter_distance_z1z2(z1, z2)
    return d.to_value(u.Mpc)


@functools.lru_cache(maxsize=4096)
def _dA_cached(key: _CosmoKey, z1: float, z2: float) -> float:
    if z1 == 0.0:
        return float(key.cosmo.angular_diameter_distance(z2).to_value(u.Mpc))
    if getattr(key.cosmo, "Ok0", None) == 0:
        # flat: D_A(z1, z2) = (D_C(z2) - D_C(z1)) / (1 + z2), from the distances of
        # single redshifts (cached; a campaign has few plane redshifts and one source
        # redshift per image) instead of one integral per pair of redshifts
        return (_dC_cached(key, z2) - _dC_cached(key, z1)) / (1.0 + z2)
    return float(_da12(key.cosmo, z1, z2))


@functools.lru_cache(maxsize=4096)
def _dC_cached(key: _CosmoKey, z: float) -> float:
    return float(key.cosmo.comoving_distance(z).to_value(u.Mpc))


def angular_diameter_distance_z1z2(z1, z2, cosmo=None) -> np.ndarray:
    """Angular diameter distance between redshifts ``z1 < z2``.

    *Unit: physical Mpc.* Scalars are cached; arrays broadcast.
    """
    cosmo = _default(cosmo)
    z1 = _check_z("z1", z1, allow_zero=True)
    z2 = _check_z("z2", z2)
    if np.any(z2 <= z1):
        raise ValueError(f"z2 must be > z1; got z1={z1}, z2={z2}")
    if z1.ndim == 0 and z2.ndim == 0:
        return np.float64(_dA_cached(_cosmo_key(cosmo), float(z1), float(z2)))  # type: ignore[return-value]
    if np.all(z1 == 0):
        return np.asarray(cosmo.angular_diameter_distance(z2).to_value(u.Mpc), dtype=np.float64)
    z1, z2 = np.broadcast_arrays(z1, z2)
    return np.asarray(_da12(cosmo, z1, z2), dtype=np.float64)


def angular_diameter_distance(z, cosmo=None) -> np.ndarray:
    """Angular diameter distance to redshift ``z`` (> 0). *Unit: physical Mpc.*"""
    return angular_diameter_distance_z1z2(0.0, _check_z("z", z), cosmo)


def lens_distances(z_lens, z_source, cosmo=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(D_l, D_s, D_ls)``: angular diameter distances observer-lens, observer-source,
    lens-source. *Unit: physical Mpc.* Requires ``0 < z_lens < z_source``."""
    z_lens = _check_z("z_lens", z_lens)
    z_source = _check_z("z_source", z_source)
    if np.any(z_source <= z_lens):
        raise ValueError(f"z_source must be > z_lens; got z_lens={z_lens}, z_source={z_source}")
    d_l = angular_diameter_distance(z_lens, cosmo)
    d_s = angular_diameter_distance(z_source, cosmo)
    d_ls = angular_diameter_distance_z1z2(z_lens, z_source, cosmo)
    return d_l, d_s, d_ls


def arcsec_to_mpc(z, cosmo=None) -> np.ndarray:
    """Physical Mpc subtended by one arcsec at redshift ``z``: ``D_A(z) * arcsec``.

    *Unit: Mpc / arcsec.* (Planck18, z = 0.2: 3.408e-3.)
    """
    return angular_diameter_distance(z, cosmo) * ARCSEC_RAD


def sigma_crit(z_lens, z_source, cosmo=None) -> np.ndarray:
    r"""Critical surface density of the lens plane,
    :math:`\Sigma_{cr} = \frac{c^2}{4\pi G}\frac{D_s}{D_l D_{ls}}` (Schneider, Ehlers &
    Falco 1992, eq. 5.5), expressed per lens-plane arcsec^2.

    *Unit: M_sun / arcsec^2.* (Planck18, z_l = 0.2, z_s = 0.6: 4.37e10.)
    """
    d_l, d_s, d_ls = lens_distances(z_lens, z_source, cosmo)
    sigma_mpc2 = _C2_4PIG * d_s / (d_l * d_ls)  # M_sun / Mpc^2
    return sigma_mpc2 * (d_l * ARCSEC_RAD) ** 2


def rho_crit(z, cosmo=None) -> np.ndarray:
    r"""Critical density of the Universe at ``z``, :math:`3H(z)^2/(8\pi G)`, with the
    arcsec at redshift ``z`` (``arcsec_to_mpc(z)`` Mpc) as unit of length.

    *Unit: M_sun / arcsec^3.* (Planck18, z = 0.2: 6.17e3.)
    """
    cosmo = _default(cosmo)
    z = _check_z("z", z)
    rho_mpc3: np.ndarray
    if z.ndim == 0:
        rho_mpc3 = np.asarray(_rho_crit_cached(_cosmo_key(cosmo), float(z)))
    else:
        rho_mpc3 = np.asarray(cosmo.critical_density(z).to_value(u.M_sun / u.Mpc**3))
    return rho_mpc3 * arcsec_to_mpc(z, cosmo) ** 3


@functools.lru_cache(maxsize=4096)
def _rho_crit_cached(key: _CosmoKey, z: float) -> float:
    return float(key.cosmo.critical_density(z).to_value(u.M_sun / u.Mpc**3))


def r200_arcsec(m200, z, cosmo=None) -> np.ndarray:
    r"""Radius enclosing a mean density of 200 rho_crit(z):
    :math:`r_{200} = (3 M_{200} / (4\pi \cdot 200 \rho_c))^{1/3}`.

    *Unit: arcsec* at redshift ``z`` (M200 = 1e8 M_sun, z = 0.2: 2.68).
    """
    m200 = _check_positive("m200", m200)
    return np.cbrt(3.0 * m200 / (4.0 * np.pi * 200.0 * rho_crit(z, cosmo)))


def epl_log_amp_from_m200(m200, gamma, z_lens, z_source, cosmo=None) -> np.ndarray:
    r"""Natural log of the EPL amplitude :math:`A = \theta_E^{\gamma-1}` of a halo of
    mass ``m200`` (M_sun) and 3-D slope ``gamma`` (1 < gamma < 3), docs/simulation.md:

    .. math::

        \rho_0 = \frac{(3-\gamma) M_{200}}{4\pi r_{200}^{3-\gamma}\,\Sigma_{cr}},\qquad
        A = \frac{2\sqrt\pi\,\Gamma(\frac{\gamma-1}{2})}{(3-\gamma)\Gamma(\frac{\gamma}{2})}
            \rho_0 .

    The factors (3 - gamma) cancel; everything is summed in logs (``gammaln``), so the
    result is finite for gamma -> 1 (A ~ 1e-2 at gamma = 1.01 and M200 = 1e8 M_sun,
    whereas theta_E = A^(1/(gamma-1)) ~ 1e-199 arcsec). *Unit: ln(arcsec^(gamma-1)).*
    Vectorised over ``m200``, ``gamma`` and the redshifts (numpy broadcasting; the plane
    terms of each distinct redshift pair from :func:`plane_logs`).
    """
    return epl_log_amp_from_logs(m200, gamma, *plane_logs(z_lens, z_source, cosmo))


def epl_log_amp_from_logs(m200, gamma, ln_rho200, ln_sigma) -> np.ndarray:
    """:func:`epl_log_amp_from_m200` from the plane terms of :func:`plane_logs`
    (``ln_rho200``, ``ln_sigma``, broadcast against ``m200`` and ``gamma``).
    *Unit: ln(arcsec^(gamma-1)).*"""
    gamma = np.asarray(gamma, dtype=np.float64)
    bad = ~np.isfinite(gamma) | (gamma <= 1.0) | (gamma >= 3.0)
    if np.any(bad):
        raise ValueError(f"gamma must lie in (1, 3); got {gamma[bad].ravel()[:3]}")
    m200 = _check_positive("m200", m200)
    ln_r200 = (np.log(m200) - ln_rho200) / 3.0
    return (
        math.log(2.0 * math.sqrt(math.pi))
        + gammaln(0.5 * (gamma - 1.0))
        - gammaln(0.5 * gamma)
        + np.log(m200)
        - math.log(4.0 * math.pi)
        - (3.0 - gamma) * ln_r200
        - ln_sigma
    )


def plane_logs(z_lens, z_source, cosmo=None):
    r"""``(ln(4π/3 · 200 ρ_c(z_lens)), ln Σ_cr(z_lens, z_source))`` in arcsec units (M☉ /
    arcsec³ and M☉ / arcsec²): what :func:`epl_log_amp_from_m200` needs of a lens plane
    (ln r200 = (ln M200 − the first) / 3).

    Scalars or arrays that broadcast together; each distinct (z_lens, z_source) pair is
    evaluated once at scalar redshifts and cached, so an array of pairs gives exactly the
    values of the pairs one at a time.
    """
    key = _cosmo_key(_default(cosmo))
    if np.ndim(z_lens) == 0 and np.ndim(z_source) == 0:
        return _plane_logs(key, float(z_lens), float(z_source))
    zl, zs = np.broadcast_arrays(
        np.asarray(z_lens, dtype=np.float64), np.asarray(z_source, dtype=np.float64)
    )
    if zl.size == 0:
        return np.zeros(zl.shape), np.zeros(zl.shape)
    pairs, inverse = np.unique(
        np.stack([zl.ravel(), zs.ravel()], axis=1), axis=0, return_inverse=True
    )
    logs = np.array([_plane_logs(key, float(a), float(b)) for a, b in pairs])
    inverse = inverse.ravel()
    return logs[inverse, 0].reshape(zl.shape), logs[inverse, 1].reshape(zl.shape)


@functools.lru_cache(maxsize=65536)
def _plane_logs(key: _CosmoKey, z_lens: float, z_source: float) -> tuple[float, float]:
    rho = float(rho_crit(z_lens, key.cosmo))
    return math.log(4.0 * math.pi / 3.0 * 200.0 * rho), float(
        np.log(sigma_crit(z_lens, z_source, key.cosmo))
    )


def epl_amp_from_m200(m200, gamma, z_lens, z_source, cosmo=None) -> np.ndarray:
    r"""EPL amplitude :math:`A = \theta_E^{\gamma-1}` (``exp`` of
    :func:`epl_log_amp_from_m200`). A round EPL has kappa(1") = (3-gamma)/2 A and
    alpha(1") = A. *Unit: arcsec^(gamma-1).* Never returns theta_E.
    """
    return np.exp(epl_log_amp_from_m200(m200, gamma, z_lens, z_source, cosmo))


def _nfw_mu(c):
    """m(c) = ln(1+c) - c/(1+c), the NFW enclosed-mass function."""
    return np.log1p(c) - c / (1.0 + c)


def nfw_params_from_m200_c(m200, c200, z_lens, z_source, cosmo=None):
    r"""NFW lensing parameters ``(R_s, alpha_Rs)`` from M200 (M_sun, 200 rho_crit(z_lens))
    and concentration c200 = r200 / R_s, in lenstronomy's convention
    (``LensCosmo.nfw_physical2angle``):

    .. math::

        R_s = r_{200}/c,\quad
        \rho_0 = \frac{200}{3}\rho_c\frac{c^3}{\ln(1+c) - c/(1+c)},\quad
        \alpha_{R_s} = \frac{4\rho_0 R_s^2\,(1 + \ln\frac12)}{\Sigma_{cr}} .

    *Unit: arcsec* for both. Vectorised (numpy broadcasting).
    """
    m200 = _check_positive("m200", m200)
    c200 = _check_positive("c200", c200)
    rho_c = rho_crit(z_lens, cosmo)
    r_s = r200_arcsec(m200, z_lens, cosmo) / c200
    rho0 = 200.0 / 3.0 * rho_c * c200**3 / _nfw_mu(c200)
    alpha_rs = 4.0 * rho0 * r_s**2 * NFW_G1 / sigma_crit(z_lens, z_source, cosmo)
    return r_s, alpha_rs


def m200_c_from_nfw_params(r_s, alpha_rs, z_lens, z_source, cosmo=None):
    """Inverse of :func:`nfw_params_from_m200_c`: ``(m200 [M_sun], c200)`` from
    ``R_s`` and ``alpha_Rs`` (arcsec). c200 solves
    200/3 rho_c c^3 / m(c) = rho0 by bisection in ln c over [1e-3, 1e5]
    (the left side increases monotonically with c); relative accuracy ~1e-12.
    """
    r_s = _check_positive("r_s", r_s)
    alpha_rs = _check_positive("alpha_rs", alpha_rs)
    rho_c = rho_crit(z_lens, cosmo)
    rho0 = alpha_rs * sigma_crit(z_lens, z_source, cosmo) / (4.0 * r_s**2 * NFW_G1)
    target = np.log(rho0 / (200.0 / 3.0 * rho_c))
    lo = np.full(np.shape(target), math.log(1e-3))
    hi = np.full(np.shape(target), math.log(1e5))

    def h(lnc):
        c = np.exp(lnc)
        return 3.0 * lnc - np.log(_nfw_mu(c)) - target

    if np.any(h(lo) > 0) or np.any(h(hi) < 0):
        raise ValueError("alpha_rs / r_s imply a concentration outside [1e-3, 1e5]")
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        up = h(mid) > 0
        hi = np.where(up, mid, hi)
        lo = np.where(up, lo, mid)
    c200 = np.exp(0.5 * (lo + hi))
    m200 = 4.0 * np.pi / 3.0 * 200.0 * rho_c * (c200 * r_s) ** 3
    return m200, c200
