"""Line-of-sight (LoS) halo populations: the DG19 model as used by paltas.

Halos between observer and source are drawn in thin redshift slices of a double
cone around the optical axis (Gilman et al. 2019, arXiv:1909.02573; paltas
``LOSDG19``, Wagner-Carena et al. 2023). Per slice k, with lower edge z_k and
mid redshift z_k + dz/2, the expected number of halos is::

    N_k = δ_los · n(z_k + dz/2) · V_k · B_k,
    n(z) = ∫_{m_min}^{m_max} dn/dM(M, z) dM            [comoving Mpc⁻³]
    V_k = π (D_M(z_k + dz/2) · θ_k)² · (D_C(z_k + dz) − D_C(z_k))   [comoving Mpc³]

where dn/dM is the Sheth & Tormen (1999/2001) mass function (A = 0.3222,
a = 0.707, p = 0.3, δ_c with its redshift correction) computed by colossus,
θ_k is the cone radius (radians) at the slice, and B_k the two-halo boost of
the main-lens host (see :func:`two_halo_boost`). The count is Poisson drawn,
masses are drawn from dn/dM on [m_min, m_max] by inverse CDF, positions
uniformly in the slice's disc. Everything here is numpy float64; nothing is
rendered.

Units: masses M☉ (no h), distances comoving Mpc (no h), angles arcsec. The
colossus cosmology is ``planck18`` (set once, cached; colossus works in h-units
internally and every conversion is done at the call site).

Caching: the per-slice mass-function integral and CDF depend only on the slice
redshift and the mass range, not on the lens, so they are cached per
(slice grid, mass range, grid size). Expected counts per system are not cached:
they cost ~1 ms (see ``docs/simulation.md``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from subslope.ragged import counts_to_offsets, counts_to_starts, draw_per_system
from subslope.simulation.los_cone import (
    DEFAULT_CONFIG,
    LosConfig,
    _check_delta,
    _check_positive,
    _check_redshifts,
    _mass_tables,
    host_m200_from_epl,
    slice_table,
    two_halo_boosts,
)

__all__ = [
    "LosConfig",
    "LosHalos",
    "LosBatch",
    "expected_counts",
    "sample_los",
    "sample_los_batch",
    "LosPopulation",
    "los_profiles",
]


# --------------------------------------------------------------------------------------
# configuration and containers
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LosHalos:
    """LoS halos of one system, flat float64 arrays of equal length.

    Attributes:
        z: redshift of each halo's plane (slice mid redshift).
        x, y: angular position in that plane [arcsec], cone axis at (0, 0).
        m200: halo mass [M☉].
    """

    z: np.ndarray
    x: np.ndarray
    y: np.ndarray
    m200: np.ndarray

    def __len__(self) -> int:
        return int(self.z.shape[0])


@dataclass(frozen=True)
class LosBatch:
    """LoS halos of many systems, ragged: flat arrays plus counts per system.

    Halos of system i are ``slice(offsets[i], offsets[i] + counts[i])``.
    """

    z: np.ndarray
    x: np.ndarray
    y: np.ndarray
    m200: np.ndarray
    counts: np.ndarray
    offsets: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        offsets = counts_to_starts(np.asarray(self.counts))
        object.__setattr__(self, "offsets", offsets)

    def system(self, i: int) -> LosHalos:
        """The halos of system ``i`` as a :class:`LosHalos`."""
        s = slice(int(self.offsets[i]), int(self.offsets[i] + self.counts[i]))
        return LosHalos(z=self.z[s], x=self.x[s], y=self.y[s], m200=self.m200[s])


@dataclass(frozen=True)
class LosPopulation:
    """LoS halos of many systems with the lens parameters the renderer needs.

    Ragged like :class:`LosBatch` (flat arrays + ``counts`` per system). ``z`` is each
    halo's plane redshift (a slice mid redshift shared by all systems of a scene), so
    halos group into planes by equal ``z``. Parameters follow the lenstronomy
    multi-plane convention: they give the *reduced* deflection for a source at the
    system's z_source. Fields that do not apply to ``profile`` are ``None``:

    - ``profile == "epl"``: ``amp`` (θ_E^(γ−1), arcsec^(γ−1)), ``gamma``, ``e1``, ``e2``;
    - ``profile == "nfw"``: ``c200``, ``r_s`` and ``alpha_rs`` (arcsec).
    """

    profile: str
    counts: np.ndarray
    z: np.ndarray
    x: np.ndarray
    y: np.ndarray
    m200: np.ndarray
    amp: np.ndarray | None = None
    gamma: np.ndarray | None = None
    e1: np.ndarray | None = None
    e2: np.ndarray | None = None
    c200: np.ndarray | None = None
    r_s: np.ndarray | None = None
    alpha_rs: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.profile not in ("epl", "nfw"):
            raise ValueError(f"LosPopulation.profile must be 'epl' or 'nfw', got {self.profile!r}")
        n = int(np.sum(self.counts))
        for name in ("z", "x", "y", "m200", "amp", "gamma", "e1", "e2", "c200", "r_s", "alpha_rs"):
            value = getattr(self, name)
            if value is not None and len(value) != n:
                raise ValueError(
                    f"LosPopulation.{name} has {len(value)} entries, counts sum to {n}"
                )

    @property
    def offsets(self) -> np.ndarray:
        return counts_to_starts(np.asarray(self.counts))


# --------------------------------------------------------------------------------------
# expected counts and sampling
# --------------------------------------------------------------------------------------
def expected_counts(
    z_lens: float,
    z_source: float,
    host_m200: float,
    delta_los: float,
    config: LosConfig = DEFAULT_CONFIG,
) -> np.ndarray:
    """Expected number of LoS halos in each slice (see module docstring).

    Args:
        z_lens, z_source: redshifts, 0 < z_lens < z_source.
        host_m200: host halo mass of the main lens [M☉] (two-halo term).
        delta_los: mass-function normalisation, >= 0.
        config: model knobs.

    Returns:
        float64 array, one entry per slice of :func:`slice_redshifts`.
    """
    _check_redshifts(z_lens, z_source)
    _check_delta(delta_los)
    _check_positive("host_m200", host_m200)
    table = slice_table(z_lens, z_source, config)
    n_int = _slice_mass_tables(table, config)[0]
    lam = _expected_counts(table, [z_lens], [host_m200], [delta_los], n_int, config)
    return lam[0, : table.n[0]]


def _slice_mass_tables(table, config: LosConfig):
    """``(n per slice [Mpc⁻³], stacked inverse-CDF table, ln M grid)`` of the slices of
    ``table`` (:func:`subslope.simulation.los_cone._mass_tables`, cached)."""
    return _mass_tables(
        tuple(table.z_mid.tolist()),
        float(config.m_min),
        float(config.m_max),
        int(config.n_mass_grid),
    )


def _expected_counts(table, z_lens, host_m200, delta_los, n_int, config: LosConfig):
    """(B, K) expected counts of the systems of ``table`` (0 past a system's slices);
    ``n_int`` the mass-function integral of each slice."""
    if table.z_mid.size == 0:
        return np.zeros((len(z_lens), 0))
    own = np.arange(table.z_mid.size) < table.n[:, None]
    counts = np.asarray(delta_los, dtype=np.float64)[:, None] * n_int * table.volume
    if config.two_halo:
        counts = counts * two_halo_boosts(
            table.z_lo,
            table.n,
            z_lens,
            host_m200,
            config.dz,
            config.r_min,
            config.r_max,
            config.n_two_halo_quad,
        )
    return np.where(own, counts, 0.0)


def _draw(lam: np.ndarray, z_mid: np.ndarray, radius: np.ndarray, tables, rng) -> LosHalos:
    """Poisson counts per slice, inverse-CDF masses, uniform disc positions; ``tables``
    (cdf, ln M, mass range) of :func:`subslope.simulation.los_cone._mass_tables` for
    ``z_mid`` or any grid it is a prefix of."""
    cdf, ln_m, (m_min, m_max) = tables
    n_per_slice = rng.poisson(lam)
    slice_idx = np.repeat(np.arange(lam.size), n_per_slice)
    n = slice_idx.size
    # inverse CDF: locate u in its own slice's row of the offset-stacked table
    # and interpolate linearly in ln M between the bracketing grid points
    q = rng.random(n) + 2.0 * slice_idx
    hi = np.clip(np.searchsorted(cdf, q, side="right"), 1, cdf.size - 1)
    lo = hi - 1
    width = cdf[hi] - cdf[lo]
    frac = np.where(width > 0, (q - cdf[lo]) / np.where(width > 0, width, 1.0), 0.0)
    m200 = np.exp(ln_m[lo] + np.clip(frac, 0.0, 1.0) * (ln_m[hi] - ln_m[lo]))
    np.clip(m200, m_min, m_max, out=m200)
    r = radius[slice_idx] * np.sqrt(rng.random(n))
    phi = 2.0 * np.pi * rng.random(n)
    return LosHalos(z=z_mid[slice_idx], x=r * np.cos(phi), y=r * np.sin(phi), m200=m200)


def sample_los(
    z_lens: float,
    z_source: float,
    theta_e: float,
    gamma_ml: float,
    delta_los: float,
    rng: np.random.Generator,
    config: LosConfig = DEFAULT_CONFIG,
) -> LosHalos:
    """Draw the LoS halos of one lens system.

    The host M200 comes from the main-lens EPL (``theta_e`` [arcsec], ``gamma_ml``)
    via :func:`host_m200_from_epl`. ``delta_los = 0`` gives empty arrays.

    Returns:
        :class:`LosHalos` with plane redshifts, positions [arcsec] and M200 [M☉].
    """
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    return sample_los_batch(z_lens, z_source, theta_e, gamma_ml, delta_los, rng, config).system(0)


def sample_los_batch(
    z_lens,
    z_source,
    theta_e,
    gamma_ml,
    delta_los,
    rng,
    config: LosConfig = DEFAULT_CONFIG,
) -> LosBatch:
    """Draw LoS halos for many systems (1-D parameter arrays, broadcast together).

    ``rng``: one Generator, from which the systems are drawn in order (the result equals
    successive :func:`sample_los` calls), or a sequence of one Generator per system. The
    slices, cone and expected counts of all systems are evaluated together. Returns a
    ragged :class:`LosBatch`.
    """
    params = (z_lens, z_source, theta_e, gamma_ml, delta_los)
    arrays = np.broadcast_arrays(*(np.atleast_1d(np.asarray(a, np.float64)) for a in params))
    if arrays[0].ndim != 1:
        raise ValueError(f"system parameters must be scalars or 1-D, got shape {arrays[0].shape}")
    zl, zs, theta_e, gamma_ml, delta = arrays
    if zl.size:
        _check_redshifts(zl, zs)
        _check_delta(delta)
        host = host_m200_from_epl(theta_e, gamma_ml, zl, zs)
    else:
        host = np.zeros(0)
    table = slice_table(zl, zs, config)
    n_int, cdf, ln_m = _slice_mass_tables(table, config)
    lam = _expected_counts(table, zl, host, delta, n_int, config)
    tables = (cdf, ln_m, (config.m_min, config.m_max))

    def draw(r: np.random.Generator, s: slice) -> dict[str, np.ndarray]:
        parts = [
            _draw(lam[b, :k], table.z_mid[:k], table.radius[b, :k], tables, r)
            for b, k in zip(range(s.start, s.stop), table.n[s])
        ]
        fields = {f: [getattr(p, f) for p in parts] for f in ("z", "x", "y", "m200")}
        out = {f: np.concatenate(v) if v else np.zeros(0) for f, v in fields.items()}
        return {**out, "counts": np.array([len(p) for p in parts], dtype=np.int64)}

    return LosBatch(**draw_per_system(rng, zl.size, draw))


# --------------------------------------------------------------------------------------
# lens profiles of the sampled halos
# --------------------------------------------------------------------------------------
def _group_planes(z: np.ndarray, z_source_halo: np.ndarray):
    """Indices of the halos sharing each distinct (plane z, system z_source) pair."""
    if z.size == 0:
        return []
    keys = np.stack([z, z_source_halo], axis=1)
    uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
    order = np.argsort(inverse.ravel(), kind="stable")
    bounds = np.searchsorted(inverse.ravel()[order], np.arange(uniq.shape[0] + 1))
    return [
        (float(uniq[k, 0]), float(uniq[k, 1]), order[bounds[k] : bounds[k + 1]])
        for k in range(uniq.shape[0])
    ]


def los_profiles(batch: LosBatch, scene, macro: dict, rng, *, cosmo=None) -> LosPopulation:
    """Attach lens-profile parameters to sampled LoS halos (a rendering-ready population).

    Parameters
    ----------
    batch : LosBatch
        Halos of ``B`` systems from :func:`sample_los_batch`.
    scene : subslope.simulation.scenes.Scene
        ``scene.los.profile`` selects the profile; EPL halos take their slope scatter,
        bounds and ellipticity priors from ``scene.subhalos`` ("as the subhalos"), NFW
        halos the concentration scatter of ``scene.concentration``.
    macro : dict
        Per-system arrays of length ``B``: ``z_source``; ``gamma_sub`` (EPL: the
        system's label γ); ``c_multiplier`` (NFW with ``concentration.apply_to_los``).
    rng : numpy.random.Generator, or a sequence of one Generator per system
        Draw order: EPL γ_i, e1, e2; NFW the c200 scatter (all systems field by field from
        one Generator; each system's fields from its own).

    EPL: γ_i ~ N(γ, f·γ) truncated to the γ_i bounds (f = ``gamma_scatter``), amplitude
    θ_E^(γ_i−1) = :func:`subslope.physics.cosmology.epl_amp_from_m200` (M200, γ_i, z_halo,
    z_source): lens-plane units of the halo's own plane. NFW: c200 = c_DM14(M200, z_halo)
    · 10^N(0, scatter_dex) (× the multiplier a only if ``apply_to_los``), then
    ``(R_s, α_Rs)`` from :func:`subslope.physics.cosmology.nfw_params_from_m200_c` at (z_halo,
    z_source), grouped by (plane, z_source) so that the distances are evaluated at scalar
    redshifts (cached).
    """
    from subslope.physics import cosmology as _cosmology
    from subslope.simulation.subhalos import sample_subhalo_gammas

    counts = np.asarray(batch.counts, dtype=np.int64)
    n_sys = counts.size
    z_source = np.broadcast_to(np.asarray(macro["z_source"], dtype=np.float64), (n_sys,))
    sys = np.repeat(np.arange(n_sys), counts)
    profile = scene.los.profile
    out = dict(
        profile=profile,
        counts=counts,
        z=np.asarray(batch.z, np.float64),
        x=np.asarray(batch.x, np.float64),
        y=np.asarray(batch.y, np.float64),
        m200=np.asarray(batch.m200, np.float64),
    )
    off = counts_to_offsets(counts)
    if profile == "epl":
        if "gamma_sub" not in macro:
            raise ValueError("macro has no 'gamma_sub' (label γ) but the scene's LoS halos are EPL")
        spec = scene.subhalos
        gamma_sys = np.broadcast_to(np.asarray(macro["gamma_sub"], dtype=np.float64), (n_sys,))

        def draw(r: np.random.Generator, s: slice) -> dict[str, np.ndarray]:
            n = int(off[s.stop] - off[s.start])
            gamma = sample_subhalo_gammas(
                gamma_sys[s], counts[s], r, spec.gamma_scatter, spec.gamma_bounds
            )
            return {"gamma": gamma, "e1": spec.e1.sample(r, n), "e2": spec.e2.sample(r, n)}

        drawn = draw_per_system(rng, counts.size, draw)
        amp = _cosmology.epl_amp_from_m200(
            out["m200"], drawn["gamma"], out["z"], z_source[sys], cosmo
        )
        out.update(amp=amp, **drawn)
    elif profile == "nfw":
        out.update(_nfw_fields(out, counts, z_source, macro, scene, rng, cosmo))
    else:  # pragma: no cover - Scene validates the profile
        raise ValueError(f"scene.los.profile = {profile!r} must be 'epl' or 'nfw'")
    return LosPopulation(**out)


def _nfw_fields(out, counts, z_source, macro, scene, rng, cosmo) -> dict[str, np.ndarray]:
    """``c200``, ``r_s``, ``alpha_rs`` of NFW LoS halos (see :func:`los_profiles`)."""
    from subslope.physics import concentration as _conc
    from subslope.physics import cosmology as _cosmology

    conc = scene.concentration
    n_sys = counts.size
    off = counts_to_offsets(counts)
    sys = np.repeat(np.arange(n_sys), counts)
    mult = np.ones(n_sys)
    if conc.apply_to_los and "c_multiplier" in macro:
        mult = np.broadcast_to(np.asarray(macro["c_multiplier"], dtype=np.float64), (n_sys,))

    def draw(r: np.random.Generator, s: slice) -> dict[str, np.ndarray]:
        h = slice(int(off[s.start]), int(off[s.stop]))
        if h.stop == h.start:
            return {"c200": np.zeros(0)}
        m, z = out["m200"][h], out["z"][h]
        return {"c200": _conc.sample_c200(m, z, r, 1.0, conc.scatter_dex)}

    c200 = mult[sys] * draw_per_system(rng, counts.size, draw)["c200"]
    r_s, alpha = np.empty(c200.size), np.empty(c200.size)
    for z_h, z_s, idx in _group_planes(out["z"], z_source[sys]):
        r_s[idx], alpha[idx] = _cosmology.nfw_params_from_m200_c(
            out["m200"][idx], c200[idx], z_h, z_s, cosmo
        )
    return {"c200": c200, "r_s": r_s, "alpha_rs": alpha}
