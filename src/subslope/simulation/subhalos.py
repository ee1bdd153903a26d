"""Numpy sampling of subhalo populations (no rendering).

Given the per-image (macro) draw of :func:`subslope.simulation.macro.sample_macro`, this module
draws each system's subhalos and converts them to lens-profile parameters:

- masses: ``dN/dM ∝ M^slope`` on ``[m_min, m_max]`` (default −1.9 on [1e7, 1e10] M☉),
  inverse-CDF sampling;
- slopes (EPL): γ_i ~ N(γ, f·γ) truncated to ``[1.01, 2.99]`` (``f = 0.1``), exact
  truncated-normal quantiles, γ the system's label;
- ellipticities (EPL): e1, e2 from the scene priors (default U(−0.2, 0.2));
- positions: on the arc (a random pixel of the smooth image brighter than
  ``threshold_fraction`` × its maximum, plus a uniform offset within that pixel), where
  the source stamp lands (the same rule on the image of the stamp's support) or
  uniformly over the whole field;
- lens parameters: EPL amplitude θ_E^(γ−1) (:func:`subslope.physics.cosmology.epl_amp_from_m200`),
  or NFW ``(R_s, α_Rs)`` with c200 = a · c_DM14(M, z_lens) · 10^N(0, σ_dex)
  (:mod:`subslope.physics.concentration`) and, for tNFW, the truncation radius from the
  projected distance to the lens centre.

The population of a batch of ``B`` systems is *ragged*: flat arrays of length
``N = counts.sum()`` ordered system by system, with ``counts`` (B,) and
``offsets(counts)`` (B + 1,) delimiting system ``b`` as ``[offsets[b], offsets[b+1])``.
Units: arcsec and M☉. Coordinates follow docs/design.md (pixel ``image[j, i]`` is
centred on ``x_i = (i − (W−1)/2)·Δ``, ``y_j = (j − (H−1)/2)·Δ``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from subslope.physics import concentration as _conc
from subslope.physics import cosmology as _cosmo
from subslope.physics.instrument import NPIX, PIXEL_SCALE
from subslope.ragged import counts_to_offsets, counts_to_starts, draw_per_system
from subslope.simulation.precision import SUBHALO_DTYPES, rounded
from subslope.simulation.priors import Prior, truncated_normal_quantile

__all__ = [
    "SubhaloPopulation",
    "offsets",
    "system_index",
    "sample_masses",
    "sample_subhalo_gammas",
    "ON_IMAGE",
    "arc_candidates",
    "place_on_arc",
    "place_everywhere",
    "epl_amplitudes",
    "sample_concentrations",
    "nfw_lens_parameters",
    "nfw_parameters",
    "subhalo_population",
    "sample_subhalos",
]

#: Smallest projected distance (arcsec) used for the tNFW truncation radius, so that a
#: subhalo exactly on the lens centre still gets a finite, positive r_t.
R_SUB_FLOOR = 1e-3


def _counts(counts) -> np.ndarray:
    c = np.asarray(counts)
    if c.ndim != 1 or (
        c.size
        and (not np.issubdtype(c.dtype, np.number) or np.any(c < 0) or np.any(c != np.floor(c)))
    ):
        raise ValueError(f"counts must be a 1-D array of non-negative integers, got {counts!r}")
    return c.astype(np.int64)


def offsets(counts) -> np.ndarray:
    """Start indices ``(B + 1,)``: system ``b`` owns ``[offsets[b], offsets[b + 1])``."""
    c = _counts(counts)
    return counts_to_offsets(c)


def system_index(counts) -> np.ndarray:
    """System index of every subhalo, ``(N,)`` int64 (``repeat(arange(B), counts)``)."""
    c = _counts(counts)
    return np.repeat(np.arange(c.size, dtype=np.int64), c)


@dataclass
class SubhaloPopulation:
    """Ragged subhalo population of ``B`` systems (flat arrays of length ``N``).

    Fields that do not apply to ``profile`` are ``None``: ``gamma``, ``e1``, ``e2``,
    ``amp`` for EPL only; ``c200``, ``r_s``, ``alpha_rs`` for NFW/tNFW; ``r_t`` for
    tNFW. ``amp`` is θ_E^(γ−1) in arcsec^(γ−1); ``x``, ``y``, ``r_s``, ``alpha_rs``,
    ``r_t`` in arcsec; ``mass`` = M200 in M☉.
    """

    profile: str
    counts: np.ndarray
    mass: np.ndarray
    x: np.ndarray
    y: np.ndarray
    gamma: np.ndarray | None = None
    e1: np.ndarray | None = None
    e2: np.ndarray | None = None
    amp: np.ndarray | None = None
    c200: np.ndarray | None = None
    r_s: np.ndarray | None = None
    alpha_rs: np.ndarray | None = None
    r_t: np.ndarray | None = None

    @property
    def offsets(self) -> np.ndarray:
        return offsets(self.counts)

    @property
    def system(self) -> np.ndarray:
        return system_index(self.counts)

    def arrays(self) -> dict[str, np.ndarray]:
        """All array fields that are set (``counts`` included), keyed by field name."""
        return {
            f.name: getattr(self, f.name)
            for f in fields(self)
            if f.name != "profile" and getattr(self, f.name) is not None
        }


# ---------------------------------------------------------------------------- draws
def sample_masses(
    n: int, rng: np.random.Generator, slope: float = -1.9, m_min: float = 1e7, m_max: float = 1e10
) -> np.ndarray:
    """``n`` masses (M☉) from ``dN/dM ∝ M^slope`` on ``[m_min, m_max]`` (inverse CDF)."""
    prior = Prior.from_config(
        {"dist": "power_law", "slope": slope, "low": m_min, "high": m_max}, "subhalos.mass"
    )
    return prior.sample(rng, int(n))


def sample_subhalo_gammas(
    gamma_system,
    counts,
    rng: np.random.Generator,
    scatter: float = 0.1,
    bounds: tuple[float, float] = (1.01, 2.99),
) -> np.ndarray:
    """Per-subhalo slopes γ_i ~ N(γ_b, scatter·γ_b) truncated to ``bounds``.

    ``gamma_system`` (B,) are the systems' labels, ``counts`` (B,) their subhalo
    numbers. Exact: the truncated-normal quantile of ``rng.random``
    (:func:`subslope.simulation.priors.truncated_normal_quantile`),
    no rejection. ``scatter = 0`` gives γ_i = γ_b (clipped to the bounds).
    """
    c = _counts(counts)
    g = np.asarray(gamma_system, dtype=np.float64)
    if g.shape != c.shape:
        raise ValueError(f"gamma_system shape {g.shape} must equal counts shape {c.shape}")
    lo, hi = float(bounds[0]), float(bounds[1])
    if not lo < hi:
        raise ValueError(f"bounds = {bounds!r} must satisfy low < high")
    if not 0 <= scatter < np.inf:
        raise ValueError(f"scatter = {scatter!r} must be a finite number >= 0")
    mu = np.repeat(g, c)
    u = rng.random(mu.size)
    if scatter == 0 or mu.size == 0:
        return np.clip(mu, lo, hi)
    sigma = scatter * np.abs(g)
    a, b = (lo - g) / sigma, (hi - g) / sigma
    if c.size > 1:  # one system keeps its bounds as scalars (two Φ calls in all)
        sigma, a, b = (np.repeat(v, c) for v in (sigma, a, b))
    return np.clip(mu + sigma * truncated_normal_quantile(u, a, b), lo, hi)


# ---------------------------------------------------------------------------- placement
#: Placements that pick candidate pixels of an image of the smooth model: ``arc`` (the
#: lensed source, PSF-convolved) and ``landing`` (the lensed support of the source stamp,
#: PSF-convolved: every pixel whose light comes from inside the stamp, as the reference
#: code's noisy, undenoised stamps made it).
ON_IMAGE = ("arc", "landing")


def _threshold_mask(images: np.ndarray, threshold_fraction: float) -> np.ndarray:
    if not 0.0 < threshold_fraction < 1.0:
        raise ValueError(f"threshold_fraction = {threshold_fraction!r} must lie in (0, 1)")
    peak = images.reshape(images.shape[0], -1).max(axis=1)
    return images > (threshold_fraction * peak)[:, None, None]


def arc_candidates(smooth_image, threshold_fraction: float = 0.2) -> np.ndarray:
    """Flat (row-major) indices of the pixels brighter than ``threshold_fraction`` × max.

    ``smooth_image`` (H, W) is the image of the smooth model (main lens, shear,
    multipoles and source; no lens light, no substructure). Empty when the image has no
    positive pixel.
    """
    img = np.asarray(smooth_image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"smooth_image must be 2-D (H, W), got shape {img.shape}")
    return np.flatnonzero(_threshold_mask(img[None], threshold_fraction)[0])


def _pixel_centres(flat: np.ndarray, h: int, w: int, pixel_scale: float):
    j, i = np.divmod(flat, w)
    return (i - (w - 1) / 2.0) * pixel_scale, (j - (h - 1) / 2.0) * pixel_scale


def place_on_arc(
    smooth_images,
    counts,
    rng: np.random.Generator,
    pixel_scale: float = PIXEL_SCALE,
    threshold_fraction: float = 0.2,
) -> tuple[np.ndarray, np.ndarray]:
    """Positions (arcsec) of subhalos on the bright pixels of each smooth image.

    Each subhalo of system ``b`` takes a uniformly chosen candidate pixel of
    ``smooth_images[b]`` (see :func:`arc_candidates`) and a uniform offset within it.
    Vectorised over systems and subhalos. Returns flat ``x, y`` of length
    ``counts.sum()``. Raises ``ValueError`` if a system with subhalos has no candidate.
    """
    imgs = np.asarray(smooth_images, dtype=np.float64)
    c = _counts(counts)
    if imgs.ndim != 3 or imgs.shape[0] != c.size:
        raise ValueError(
            f"smooth_images must have shape (B, H, W) with B = len(counts) = {c.size}, got "
            f"{imgs.shape}"
        )
    if not pixel_scale > 0:
        raise ValueError(f"pixel_scale = {pixel_scale!r} must be > 0 arcsec")
    _, h, w = imgs.shape
    mask = _threshold_mask(imgs, threshold_fraction).reshape(c.size, -1)
    n_cand = mask.sum(axis=1)
    empty = (n_cand == 0) & (c > 0)
    if np.any(empty):
        raise ValueError(
            f"smooth_images[{int(np.flatnonzero(empty)[0])}] has no pixel above threshold_fraction "
            f"{threshold_fraction} of its maximum (blank image?) but subhalos must be placed on it"
        )
    # each system's candidate pixels in ascending pixel index, systems one after another
    _, candidates = np.nonzero(mask)
    first = counts_to_starts(n_cand)
    sys = system_index(c)
    pick = np.minimum((rng.random(sys.size) * n_cand[sys]).astype(np.int64), n_cand[sys] - 1)
    flat = candidates[first[sys] + pick]
    x, y = _pixel_centres(flat, h, w, pixel_scale)
    off = rng.uniform(-0.5, 0.5, size=(2, sys.size)) * pixel_scale
    return x + off[0], y + off[1]


def place_everywhere(
    counts, rng: np.random.Generator, npix: int = NPIX, pixel_scale: float = PIXEL_SCALE
) -> tuple[np.ndarray, np.ndarray]:
    """Positions (arcsec) uniform over the ``npix × npix`` field of the image."""
    c = _counts(counts)
    if isinstance(npix, bool) or not isinstance(npix, (int, np.integer)) or npix < 1:
        raise ValueError(f"npix = {npix!r} must be a positive integer")
    if not pixel_scale > 0:
        raise ValueError(f"pixel_scale = {pixel_scale!r} must be > 0 arcsec")
    half = 0.5 * npix * pixel_scale
    xy = rng.uniform(-half, half, size=(2, int(c.sum())))
    return xy[0], xy[1]


# ---------------------------------------------------------------------------- conversions
def _per_system(counts, z_lens, z_source):
    c = _counts(counts)
    zl = np.broadcast_to(np.asarray(z_lens, dtype=np.float64), c.shape)
    zs = np.broadcast_to(np.asarray(z_source, dtype=np.float64), c.shape)
    return c, offsets(c), zl, zs


def epl_amplitudes(mass, gamma, counts, z_lens, z_source, cosmo=None) -> np.ndarray:
    """EPL amplitudes θ_E^(γ−1) (arcsec^(γ−1)) of a ragged population.

    ``mass``, ``gamma`` flat (N,); ``counts``, ``z_lens``, ``z_source`` per system (B,).
    :func:`subslope.physics.cosmology.epl_amp_from_m200` with each system's redshifts
    repeated over its subhalos (its plane terms evaluated once per system).
    """
    c, _, zl, zs = _per_system(counts, z_lens, z_source)
    mass = np.asarray(mass, dtype=np.float64)
    gamma = np.asarray(gamma, dtype=np.float64)
    if not mass.size:
        return mass.copy()
    live = c > 0
    ln_rho200, ln_sigma = _cosmo.plane_logs(zl[live], zs[live], cosmo)
    return np.exp(
        _cosmo.epl_log_amp_from_logs(
            mass, gamma, np.repeat(ln_rho200, c[live]), np.repeat(ln_sigma, c[live])
        )
    )


def sample_concentrations(
    mass, counts, z_lens, rng: np.random.Generator, multiplier=1.0, scatter_dex: float = 0.1
) -> np.ndarray:
    """c200 = ``multiplier`` · c_DM14(M200, z_lens) · 10^N(0, ``scatter_dex``) of a ragged
    population (``multiplier`` scalar or per system (B,))."""
    c = _counts(counts)
    zl = np.broadcast_to(np.asarray(z_lens, dtype=np.float64), c.shape)
    mass = np.asarray(mass, dtype=np.float64)
    mult = np.broadcast_to(np.asarray(multiplier, dtype=np.float64), c.shape)
    if np.any(~np.isfinite(mult) | (mult <= 0)):
        raise ValueError(f"multiplier = {multiplier!r} must be finite and > 0")
    if not mass.size:
        return mass.copy()
    sys = system_index(c)
    return mult[sys] * _conc.sample_c200(
        mass, zl[sys], rng, multiplier=1.0, scatter_dex=scatter_dex
    )


def nfw_lens_parameters(
    mass, c200, counts, z_lens, z_source, r_sub=None, cosmo=None
) -> dict[str, np.ndarray]:
    """NFW ``(R_s, α_Rs)`` (arcsec) of a ragged population from M200 and c200
    (:func:`subslope.physics.cosmology.nfw_params_from_m200_c`); with ``r_sub`` (flat (N,),
    projected distance to the lens centre in arcsec, floored at ``R_SUB_FLOOR``) also the
    tNFW truncation radius ``r_t`` (arcsec) of :mod:`subslope.physics.concentration`."""
    c, off, zl, zs = _per_system(counts, z_lens, z_source)
    mass = np.asarray(mass, dtype=np.float64)
    c200 = np.asarray(c200, dtype=np.float64)
    r_s, alpha = np.empty_like(mass), np.empty_like(mass)
    r_t = None if r_sub is None else np.empty_like(mass)
    for b in np.flatnonzero(c):
        s = slice(off[b], off[b + 1])
        r_s[s], alpha[s] = _cosmo.nfw_params_from_m200_c(
            mass[s], c200[s], float(zl[b]), float(zs[b]), cosmo
        )
        if r_t is not None:
            r = np.maximum(np.asarray(r_sub, dtype=np.float64)[s], R_SUB_FLOOR)
            r_t[s] = _conc.truncation_radius_arcsec(mass[s], r, float(zl[b]), cosmo)
    out = {"r_s": r_s, "alpha_rs": alpha}
    if r_t is not None:
        out["r_t"] = r_t
    return out


def nfw_parameters(
    mass,
    counts,
    z_lens,
    z_source,
    rng: np.random.Generator,
    multiplier=1.0,
    scatter_dex: float = 0.1,
    r_sub=None,
    cosmo=None,
) -> dict[str, np.ndarray]:
    """NFW (and tNFW) lens parameters of a ragged population: ``c200`` drawn by
    :func:`sample_concentrations`, then :func:`nfw_lens_parameters`. Returns a dict with
    ``c200``, ``r_s``, ``alpha_rs`` [, ``r_t``]."""
    c200 = sample_concentrations(mass, counts, z_lens, rng, multiplier, scatter_dex)
    return {"c200": c200, **nfw_lens_parameters(mass, c200, counts, z_lens, z_source, r_sub, cosmo)}


def subhalo_population(
    profile: str, counts, drawn: dict[str, np.ndarray], macro, cosmo=None
) -> SubhaloPopulation:
    """The population with its lens parameters derived from the drawn fields.

    ``drawn``: ``mass``, ``x``, ``y`` and ``gamma``, ``e1``, ``e2`` (EPL) or ``c200``
    (NFW/tNFW), as drawn or as read from a shard; ``macro`` the systems' ``z_lens``,
    ``z_source`` (and ``lens_x``, ``lens_y`` for tNFW). The simulation and
    :mod:`subslope.simulation.rerender` both build populations here, so a stored
    population gives back the renderer's inputs exactly.
    """
    c = _counts(counts)
    drawn = {k: np.asarray(v, dtype=np.float64) for k, v in drawn.items()}
    zl, zs = macro["z_lens"], macro["z_source"]
    if profile == "epl":
        amp = epl_amplitudes(drawn["mass"], drawn["gamma"], c, zl, zs, cosmo)
        return SubhaloPopulation(profile=profile, counts=c, amp=amp, **drawn)
    r_sub = None
    if profile == "tnfw":
        sys = system_index(c)
        lx = np.asarray(macro["lens_x"], dtype=np.float64)[sys]
        ly = np.asarray(macro["lens_y"], dtype=np.float64)[sys]
        r_sub = np.hypot(drawn["x"] - lx, drawn["y"] - ly)
    derived = nfw_lens_parameters(drawn["mass"], drawn["c200"], c, zl, zs, r_sub, cosmo)
    return SubhaloPopulation(profile=profile, counts=c, **drawn, **derived)


def _heaviest_first(counts: np.ndarray, drawn: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Each system's subhalos in order of decreasing mass (compresses the stored masses)."""
    order = np.lexsort((-drawn["mass"], system_index(counts)))
    return {k: v[order] for k, v in drawn.items()}


# ---------------------------------------------------------------------------- driver
def sample_subhalos(
    scene,
    macro: dict[str, np.ndarray],
    rng,
    smooth_images=None,
    *,
    npix: int = 100,
    pixel_scale: float = PIXEL_SCALE,
    cosmo=None,
) -> SubhaloPopulation:
    """Subhalo population of the systems of one macro draw.

    Parameters
    ----------
    scene : subslope.simulation.scenes.Scene
    macro : dict
        Output of :func:`subslope.simulation.macro.sample_macro` (``n_sub``, ``gamma_sub``,
        ``z_lens``, ``z_source``, ``lens_x``, ``lens_y``, ``c_multiplier`` as needed).
        Without ``n_sub`` (subhalos off) every count is 0.
    rng : numpy.random.Generator, or a sequence of one Generator per system
        One Generator: every system's draws from it, field by field. One per system: each
        system's draws from its own, in the same field order, so that a system's subhalos
        do not depend on the other systems of the batch.
    smooth_images : array (B, H, W), optional
        Smooth-model images; required for ``placement='arc'`` when any count > 0.
    npix, pixel_scale : int, float
        Field for ``placement='everywhere'`` (and pixel size for ``'arc'``).

    Draw order (fixed): masses, γ_i (EPL), e1, e2 (EPL), positions, c200 scatter. Each
    drawn field is then rounded to its stored dtype
    (:data:`subslope.simulation.precision.SUBHALO_DTYPES`), each system's subhalos are
    ordered by decreasing mass, and the lens parameters are derived from the rounded
    values (:func:`subhalo_population`).
    """
    spec = scene.subhalos
    n_img = macro["z_lens"].shape[0]
    counts = _counts(macro["n_sub"]) if "n_sub" in macro else np.zeros(n_img, dtype=np.int64)
    if spec.placement in ON_IMAGE and smooth_images is None and counts.sum():
        raise ValueError(
            f"scene {scene.name!r} places subhalos by placement {spec.placement!r}: pass "
            "smooth_images (B, H, W)"
        )

    def draw(r: np.random.Generator, s: slice) -> dict[str, np.ndarray]:
        smooth = None if smooth_images is None else smooth_images[s]
        m_s = {k: v[s] for k, v in macro.items()}
        return _draw_fields(scene, m_s, counts[s], r, smooth, npix, pixel_scale)

    drawn = draw_per_system(rng, n_img, draw)
    bounds = {"gamma": spec.gamma_bounds}
    drawn = {
        k: rounded(v, SUBHALO_DTYPES[k], f"subhalos.{k}", bounds.get(k)) for k, v in drawn.items()
    }
    return subhalo_population(spec.profile, counts, _heaviest_first(counts, drawn), macro, cosmo)


def _draw_fields(
    scene, macro, counts, rng: np.random.Generator, smooth_images, npix, pixel_scale
) -> dict[str, np.ndarray]:
    """The drawn fields of :func:`sample_subhalos` (float64, before rounding)."""
    spec = scene.subhalos
    n = int(counts.sum())
    drawn = {"mass": spec.mass.sample(rng, n)}
    if spec.profile == "epl":
        if "gamma_sub" not in macro:
            raise ValueError("macro has no 'gamma_sub' (label γ) but the scene's subhalos are EPL")
        drawn["gamma"] = sample_subhalo_gammas(
            macro["gamma_sub"], counts, rng, spec.gamma_scatter, spec.gamma_bounds
        )
        drawn["e1"] = spec.e1.sample(rng, n)
        drawn["e2"] = spec.e2.sample(rng, n)
    if spec.placement in ON_IMAGE:
        if smooth_images is None:  # no subhalos (checked by the caller)
            x = y = np.zeros(0)
        else:
            x, y = place_on_arc(smooth_images, counts, rng, pixel_scale, spec.threshold_fraction)
    else:
        x, y = place_everywhere(counts, rng, npix, pixel_scale)
    drawn["x"], drawn["y"] = x, y
    if spec.profile != "epl":
        drawn["c200"] = sample_concentrations(
            drawn["mass"],
            counts,
            macro["z_lens"],
            rng,
            macro.get("c_multiplier", np.ones(counts.size)),
            scene.concentration.scatter_dex,
        )
    return drawn
