"""The DG19 line-of-sight halo model: its configuration, the slices and cone of the
light cone, the Sheth-Tormen mass function and the two-halo boost of the main-lens host
(Gilman et al. 2019, arXiv:1909.02573; paltas ``LOSDG19``). Pure numpy float64; the
colossus cosmology is ``planck18`` (set once, cached). :mod:`subslope.simulation.los_halos`
draws populations from it.

Units: masses M☉ (no h), distances comoving Mpc (no h), angles arcsec.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from subslope.physics.cosmology import epl_log_amp_from_m200

__all__ = [
    "ARCSEC",
    "LosConfig",
    "DEFAULT_CONFIG",
    "colossus_cosmology",
    "comoving_distance",
    "slice_redshifts",
    "cone_radius_arcsec",
    "SliceTable",
    "slice_table",
    "slice_volumes",
    "sheth_tormen_dndm",
    "mass_function_integral",
    "host_m200_from_epl",
    "host_bias",
    "two_halo_boost",
    "two_halo_boosts",
]

ARCSEC = math.pi / 648000.0  # radians per arcsec
_COLOSSUS_NAME = "planck18"


@dataclass(frozen=True)
class LosConfig:
    """Knobs of the DG19 LoS model (defaults: docs/simulation.md / the reference code).

    Attributes:
        m_min, m_max: mass range of rendered halos [M☉], 0 < m_min < m_max.
        z_min: lower edge of the first redshift slice.
        dz: slice thickness in redshift.
        cone_diameter: opening diameter of the cone up to the lens plane [arcsec].
        opening_factor: how far the rear cone closes towards the source, in [0, 1]
            (1 would close it to a point at z_source); paltas ``angle_buffer``.
        r_min, r_max: comoving distance range [Mpc] from the lens of the two-halo
            term (r_max gates a slice, r_min excludes the host's own halo).
        two_halo: include the host's two-halo boost.
        n_mass_grid: points of the log-mass grid of the inverse-CDF table.
        n_two_halo_quad: points per slice to average the correlation function.
    """

    m_min: float = 1e7
    m_max: float = 1e10
    z_min: float = 0.01
    dz: float = 0.01
    cone_diameter: float = 4.0
    opening_factor: float = 0.8
    r_min: float = 0.5
    r_max: float = 10.0
    two_halo: bool = True
    n_mass_grid: int = 2048
    n_two_halo_quad: int = 100

    def __post_init__(self) -> None:
        _check_positive("m_min", self.m_min)
        _check_positive("m_max", self.m_max)
        if not self.m_min < self.m_max:
            raise ValueError(
                f"m_min must be < m_max, got m_min={self.m_min:g}, m_max={self.m_max:g} M☉"
            )
        _check_positive("z_min", self.z_min)
        _check_positive("dz", self.dz)
        _check_positive("cone_diameter", self.cone_diameter)
        if not 0.0 <= self.opening_factor <= 1.0:
            raise ValueError(f"opening_factor must be in [0, 1], got {self.opening_factor!r}")
        if not (math.isfinite(self.r_min) and self.r_min >= 0.0):
            raise ValueError(f"r_min must be a finite number >= 0 Mpc, got {self.r_min!r}")
        if not (math.isfinite(self.r_max) and self.r_max > self.r_min):
            raise ValueError(
                f"r_max must be finite and > r_min={self.r_min!r} Mpc, got {self.r_max!r}"
            )
        if int(self.n_mass_grid) != self.n_mass_grid or self.n_mass_grid < 16:
            raise ValueError(f"n_mass_grid must be an integer >= 16, got {self.n_mass_grid!r}")
        if int(self.n_two_halo_quad) != self.n_two_halo_quad or self.n_two_halo_quad < 2:
            raise ValueError(
                f"n_two_halo_quad must be an integer >= 2, got {self.n_two_halo_quad!r}"
            )


# --------------------------------------------------------------------------------------
# validation helpers
# --------------------------------------------------------------------------------------
def _check_positive(name: str, value) -> None:
    if not np.all(np.isfinite(value) & (np.asarray(value) > 0)):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")


def _check_redshifts(z_lens, z_source) -> None:
    _check_positive("z_lens", z_lens)
    if not np.all(np.isfinite(z_source) & (np.asarray(z_source) > z_lens)):
        raise ValueError(f"z_source must be > z_lens={z_lens!r}, got z_source={z_source!r}")


def _check_delta(delta_los) -> None:
    if not np.all(np.isfinite(delta_los) & (np.asarray(delta_los) >= 0)):
        raise ValueError(f"delta_los must be a finite number >= 0, got {delta_los!r}")


DEFAULT_CONFIG = LosConfig()


# --------------------------------------------------------------------------------------
# colossus cosmology (set once)
# --------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def _colossus_cosmology():
    from colossus.cosmology import cosmology

    return cosmology.setCosmology(_COLOSSUS_NAME, persistence="")


def colossus_cosmology():
    """The cached colossus ``planck18`` cosmology, made colossus' current one."""
    from colossus.cosmology import cosmology

    cosmo = _colossus_cosmology()
    if cosmology.current_cosmo is not cosmo:
        cosmology.setCurrent(cosmo)
    return cosmo


_Z_TABLE_MAX = 20.0


@functools.lru_cache(maxsize=1)
def _comoving_distance_spline():
    """Cubic-spline antiderivative of c/H(z) [Mpc] on 0 <= z <= 20.

    colossus' ``comovingDistance`` runs one quadrature per redshift (~0.3 ms
    each); this table agrees with it to < 1e-6 relative.
    """
    from scipy.interpolate import CubicSpline

    cosmo = _colossus_cosmology()
    z = np.linspace(0.0, _Z_TABLE_MAX, 20001)
    hubble_distance = 299792.458 / (100.0 * cosmo.h)  # c / H0 [Mpc]
    return CubicSpline(z, hubble_distance / cosmo.Ez(z)).antiderivative()


def comoving_distance(z) -> np.ndarray:
    """Line-of-sight comoving distance from z = 0 [Mpc] (flat cosmology)."""
    z = np.asarray(z, dtype=np.float64)
    if np.any((z < 0) | (z > _Z_TABLE_MAX)):
        raise ValueError(f"redshift must be in [0, {_Z_TABLE_MAX}], got {z!r}")
    return np.asarray(_comoving_distance_spline()(z), dtype=np.float64)


# --------------------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------------------
def slice_redshifts(
    z_source: float, dz: float = 0.01, z_min: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """Lower edges and mid redshifts of the LoS slices.

    Slices start at ``z_min`` and step by ``dz``; a slice is kept while its lower
    edge is < ``z_source − dz`` (paltas: ``arange(z_min, z_source − dz, dz)``),
    so every slice ends below the source. Edges are rounded to 10 decimals so the
    grid is the same for every system. Halos of a slice sit at ``z_lo + dz/2``.
    Slices are not split at the lens: a slice containing ``z_lens`` is an
    ordinary slice (its halos sit at its mid redshift, in front of or behind the
    main-lens plane, which stays at ``z_lens``).

    Returns:
        (z_lo, z_mid), float64 arrays of equal length (possibly empty).
    """
    _check_positive("dz", dz)
    _check_positive("z_min", z_min)
    _check_positive("z_source", z_source)
    z_lo = np.round(z_min + dz * np.arange(_slice_count(z_source, dz, z_min), dtype=np.float64), 10)
    return z_lo, z_lo + 0.5 * dz


def _slice_count(z_source: float, dz: float, z_min: float) -> int:
    """Number of slices of :func:`slice_redshifts` in front of a source at ``z_source``."""
    return max(math.ceil(round((z_source - dz - z_min) / dz, 9)), 0)


def cone_radius_arcsec(
    z, z_lens, z_source, cone_diameter: float = 4.0, opening_factor: float = 0.8
) -> np.ndarray:
    """Angular radius [arcsec] of the LoS double cone at redshift ``z``.

    Up to the lens (z <= z_lens) the radius is ``cone_diameter / 2``. Behind it
    the radius is multiplied by ``1 − f · D_s · D_lz / (D_ls · D_z)`` with comoving
    distances D_s = D(0, z_s), D_ls = D(z_l, z_s), D_lz = D(z_l, z), D_z = D(0, z)
    and f = ``opening_factor`` (paltas ``cone_angle_to_radius``); it decreases
    monotonically to ``(1 − f) · cone_diameter / 2`` at z_source. ``z``, ``z_lens`` and
    ``z_source`` broadcast (e.g. slices (K,) against systems (B, 1)).
    """
    _check_redshifts(z_lens, z_source)
    _check_positive("cone_diameter", cone_diameter)
    z, z_lens, z_source = np.broadcast_arrays(
        *(np.asarray(v, dtype=np.float64) for v in (z, z_lens, z_source))
    )
    radius = np.full(z.shape, 0.5 * cone_diameter)
    behind = z > z_lens
    if np.any(behind):
        d_l = comoving_distance(z_lens[behind])
        d_s = comoving_distance(z_source[behind])
        d_z = comoving_distance(z[behind])
        shrink = opening_factor * d_s * (d_z - d_l) / ((d_s - d_l) * d_z)
        radius[behind] *= 1.0 - shrink
    return radius


@dataclass(frozen=True)
class SliceTable:
    """The slices of ``B`` systems on one grid (:func:`slice_table`).

    Attributes:
        z_lo, z_mid: (K,) lower edges and mid redshifts of the slices of the system with
            the farthest source; system b owns the first ``n[b]`` of them.
        n: (B,) number of slices of each system.
        radius: (B, K) cone radius [arcsec] at each mid redshift.
        volume: (B, K) comoving volume [Mpc³] of each slice of each cone.
    """

    z_lo: np.ndarray
    z_mid: np.ndarray
    n: np.ndarray
    radius: np.ndarray
    volume: np.ndarray


def slice_table(z_lens, z_source, config: LosConfig = DEFAULT_CONFIG) -> SliceTable:
    """Slices, cone radii and slice volumes of systems ``z_lens``, ``z_source`` (B,).

    V = π (D_M(z_mid) θ(z_mid))² (D_C(z_lo + dz) − D_C(z_lo)), θ in radians; slices as
    in :func:`slice_redshifts` (the grid of every system is a prefix of the farthest one's).
    """
    z_lens = np.atleast_1d(np.asarray(z_lens, dtype=np.float64))
    z_source = np.atleast_1d(np.asarray(z_source, dtype=np.float64))
    _check_redshifts(z_lens, z_source)
    n = np.array([_slice_count(float(v), config.dz, config.z_min) for v in z_source], np.int64)
    z_far = float(z_source.max()) if z_source.size else config.z_min
    z_lo, z_mid = slice_redshifts(z_far, config.dz, config.z_min)
    radius = cone_radius_arcsec(
        z_mid, z_lens[:, None], z_source[:, None], config.cone_diameter, config.opening_factor
    )
    d = comoving_distance(np.stack([z_lo, z_mid, z_lo + config.dz]))
    volume = np.pi * (d[1] * (ARCSEC * radius)) ** 2 * (d[2] - d[0])
    return SliceTable(z_lo=z_lo, z_mid=z_mid, n=n, radius=radius, volume=volume)


def slice_volumes(z_lens: float, z_source: float, config: LosConfig = DEFAULT_CONFIG) -> np.ndarray:
    """Comoving volume [Mpc³] of each slice of the cone (see :func:`slice_redshifts`
    and :func:`slice_table`)."""
    table = slice_table(z_lens, z_source, config)
    return table.volume[0, : table.n[0]]


# --------------------------------------------------------------------------------------
# mass function
# --------------------------------------------------------------------------------------
def sheth_tormen_dndm(m, z: float) -> np.ndarray:
    """Sheth–Tormen dn/dM [comoving Mpc⁻³ M☉⁻¹] at masses ``m`` [M☉], redshift ``z``.

    colossus ``massFunction(model='sheth99')`` (A = 0.3222, a = 0.707, p = 0.3;
    the same f(ν) paltas calls "Sheth Tormen 2001"), with the redshift-corrected
    δ_c as in paltas, converted from h-units: M = M_h / h, n = n_h · h³.
    """
    from colossus.lss import mass_function

    cosmo = colossus_cosmology()
    h = cosmo.h
    m = np.asarray(m, dtype=np.float64)
    dndlnm = mass_function.massFunction(
        m * h,
        float(z),
        q_in="M",
        q_out="dndlnM",
        mdef="fof",
        model="sheth99",
        deltac_args={"corrections": True},
    )
    return np.asarray(dndlnm, dtype=np.float64) * h**3 / m


@functools.lru_cache(maxsize=4096)
def _mass_table_one(z_mid: float, m_min: float, m_max: float, n_grid: int):
    ln_m = np.linspace(math.log(m_min), math.log(m_max), n_grid)
    m = np.exp(ln_m)
    dndlnm = sheth_tormen_dndm(m, z_mid) * m
    steps = 0.5 * (dndlnm[1:] + dndlnm[:-1]) * np.diff(ln_m)
    cum = np.concatenate([[0.0], np.cumsum(steps)])
    return cum[-1], cum / cum[-1]


@functools.lru_cache(maxsize=256)
def _mass_tables(z_mid: tuple, m_min: float, m_max: float, n_grid: int):
    """Per-slice integral n [Mpc⁻³] and an offset-stacked inverse-CDF table.

    Row k of the CDF is shifted by 2k so that all rows form one increasing
    sequence: a uniform u in slice k is looked up at u + 2k (see ``_draw``).
    """
    ln_m = np.linspace(math.log(m_min), math.log(m_max), n_grid)
    if not z_mid:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    rows = [_mass_table_one(z, m_min, m_max, n_grid) for z in z_mid]
    integral = np.array([r[0] for r in rows])
    cdf = np.stack([r[1] for r in rows]) + 2.0 * np.arange(len(rows))[:, None]
    for arr in (integral, cdf):
        arr.setflags(write=False)
    flat_ln_m = np.tile(ln_m, len(rows))
    flat_ln_m.setflags(write=False)
    return integral, cdf.ravel(), flat_ln_m


def mass_function_integral(
    z, m_min: float = 1e7, m_max: float = 1e10, n_grid: int = 2048
) -> np.ndarray:
    """∫_{m_min}^{m_max} dn/dM dM [comoving Mpc⁻³] at each redshift in ``z``."""
    LosConfig(m_min=m_min, m_max=m_max, n_mass_grid=n_grid)  # validates
    z = np.atleast_1d(np.asarray(z, dtype=np.float64))
    key = tuple(float(v) for v in np.round(z, 10))
    return _mass_tables(key, float(m_min), float(m_max), int(n_grid))[0].copy()


# --------------------------------------------------------------------------------------
# host halo and two-halo term
# --------------------------------------------------------------------------------------
def host_m200_from_epl(theta_e, gamma, z_lens, z_source) -> np.ndarray:
    """Host M200 [M☉] of a main-lens EPL with Einstein radius ``theta_e`` [arcsec].

    Inverts the EPL mass relation of docs/simulation.md
    (:func:`subslope.physics.cosmology.epl_log_amp_from_m200`): since r200 ∝ M^(1/3), the
    amplitude is θ_E^(γ−1) = K(γ) M^(γ/3), so M = (θ_E^(γ−1) / K(γ))^(3/γ) with
    ln K = ln A(M = 1 M☉). Done in logs; vectorised over ``theta_e``, ``gamma`` and the
    redshifts.
    """
    _check_redshifts(z_lens, z_source)
    theta_e = np.asarray(theta_e, dtype=np.float64)
    gamma = np.asarray(gamma, dtype=np.float64)
    if np.any(~np.isfinite(theta_e)) or np.any(theta_e <= 0):
        raise ValueError(f"theta_e must be finite and > 0 arcsec, got {theta_e!r}")
    if np.any(~np.isfinite(gamma)) or np.any((gamma <= 1) | (gamma >= 3)):
        raise ValueError(f"gamma must lie in (1, 3), got {gamma!r}")
    ln_k = epl_log_amp_from_m200(1.0, gamma, z_lens, z_source)
    ln_amp = (gamma - 1.0) * np.log(theta_e)
    return np.exp(3.0 / gamma * (ln_amp - ln_k))


def host_bias(host_m200, z_lens):
    """Linear halo bias of the host (colossus Tinker et al. 2010, M200c); scalars or
    arrays that broadcast."""
    from colossus.lss import bias

    _check_positive("host_m200", host_m200)
    _check_positive("z_lens", z_lens)
    cosmo = colossus_cosmology()
    b = bias.haloBias(
        np.asarray(host_m200, dtype=np.float64) * cosmo.h, z_lens, mdef="200c", model="tinker10"
    )
    return float(b) if np.ndim(b) == 0 else np.asarray(b, dtype=np.float64)


def two_halo_boost(
    z_lo,
    z_lens: float,
    host_m200: float,
    dz: float = 0.01,
    r_min: float = 0.5,
    r_max: float = 10.0,
    n_quad: int = 100,
) -> np.ndarray:
    """Two-halo boost 1 + ⟨ξ_lin(r, z_lens)⟩ b(M_host) of slices [z_lo, z_lo + dz].

    Following paltas: a slice is boosted only if its point nearest to the lens is
    within comoving distance ``r_max`` [Mpc]; the average of the linear matter
    correlation function (colossus, at z_lens) is then taken over ``n_quad``
    equally spaced redshifts of the slice, leaving out points closer than
    ``r_min`` [Mpc] (inside the host). All other slices get exactly 1.
    """
    z_lo = np.atleast_1d(np.asarray(z_lo, dtype=np.float64))
    return two_halo_boosts(z_lo, [z_lo.size], [z_lens], [host_m200], dz, r_min, r_max, n_quad)[0]


def two_halo_boosts(
    z_lo, n_slices, z_lens, host_m200, dz=0.01, r_min=0.5, r_max=10.0, n_quad=100
) -> np.ndarray:
    """:func:`two_halo_boost` of ``B`` systems (``n_slices``, ``z_lens``, ``host_m200``
    (B,)) on the slice grid ``z_lo`` (K,): (B, K), 1 past each system's ``n_slices``.

    ξ_lin(r, z) = ξ_lin(r, 0) D₊(z)² (colossus' own relation), so the correlation function
    is interpolated once for the slices of all systems.
    """
    z_lens = np.asarray(z_lens, dtype=np.float64)
    host_m200 = np.asarray(host_m200, dtype=np.float64)
    _check_positive("host_m200", host_m200)
    _check_positive("z_lens", z_lens)
    z_lo = np.asarray(z_lo, dtype=np.float64)
    boost = np.ones((z_lens.size, z_lo.size))
    if z_lo.size == 0:
        return boost
    cosmo = colossus_cosmology()
    d_lens = comoving_distance(z_lens)
    # the nearest point of each slice to the lens (z_lens itself if inside)
    z_near = np.clip(z_lens[:, None], z_lo, z_lo + dz)
    own = np.arange(z_lo.size) < np.asarray(n_slices)[:, None]
    gated = own & (np.abs(comoving_distance(z_near) - d_lens[:, None]) < r_max)
    if not np.any(gated):
        return boost
    rows, cols = np.nonzero(gated)
    quad = z_lo[cols, None] + dz * np.linspace(0.0, 1.0, n_quad)[None, :]
    r = np.abs(comoving_distance(quad) - d_lens[rows, None])
    keep = r > r_min
    xi = np.zeros(r.shape)
    if np.any(keep):
        growth2 = np.broadcast_to((cosmo.growthFactor(z_lens) ** 2)[rows, None], r.shape)
        xi[keep] = cosmo.correlationFunction(r[keep] * cosmo.h, 0.0) * growth2[keep]
    n_keep = keep.sum(axis=1)
    mean_xi = np.where(n_keep > 0, xi.sum(axis=1) / np.maximum(n_keep, 1), 0.0)
    boost[rows, cols] = 1.0 + mean_xi * host_bias(host_m200[rows], z_lens[rows])
    return boost
