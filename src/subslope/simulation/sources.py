"""COSMOS galaxies as the lensed sources of a scene: the catalogue folders of a config,
the galaxies of a split, each stamp cleaned of its sky noise and placed at its image's
source redshift (``docs/simulation.md``, "Sources").

Cleaning (``simulation.sources.clean``, :func:`subslope.io.cosmos.clean_stamp`) keeps
the central galaxy's footprint and zeroes the stamp's sky noise around it; with
``denoise: wavelet`` the stamp is first denoised (:func:`subslope.io.cosmos.denoise_stamp`),
which leaves ~⅓ of its noise inside the footprint
(:func:`subslope.io.cosmos.residual_noise_ratio`). Renormalising a faint stamp to a bright
magnitude multiplies the noise left inside that footprint too: :func:`noise_fraction` is
that noise, once placed at ``reference_z_source``, renormalised to the brightest
magnitude of ``mag_renormalize`` and seen through the PSF, as a fraction of the
detector's background σ per pixel. A galaxy above ``max_noise_fraction`` is dropped
(``noisy: drop``) or dimmed (``noisy: dim``): its magnitudes are drawn from the brightest
at which it meets the limit (:func:`brightest_magnitude`) to the faintest of
``mag_renormalize``, and it is dropped only when that leaves less than
``min_magnitude_range``.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from subslope.io.cosmos import (
    CosmosCatalog,
    CosmosCuts,
    clean_stamp,
    denoise_stamp,
    normalize_to_magnitude,
    place_at_redshift,
    residual_noise_ratio,
    split_idents,
)
from subslope.physics.light.pixelated import pad_stamps

__all__ = [
    "SOURCE_COLUMNS",
    "catalog_at",
    "cosmos_folders",
    "source_split",
    "source_table",
    "noise_fraction",
    "brightest_magnitude",
    "place_source",
    "pixelated_sources",
    "landing_stamps",
    "draw_sources",
    "cleaning_examples",
]

log = logging.getLogger(__name__)

#: Columns of :func:`source_table`.
SOURCE_COLUMNS = (
    "ident",
    "folder",
    "mag_auto",
    "zphot",
    "nx",
    "ny",
    "peak_snr",
    "footprint_fraction",
    "noise_ratio",
    "noise_fraction",
    "brightest_mag",
    "selected",
    "split",
)


@functools.lru_cache(maxsize=8)
def catalog_at(folders: tuple[str, ...] | str) -> CosmosCatalog:
    """The (cached) catalogue of one folder or a tuple of folders."""
    return CosmosCatalog.load(list(folders) if isinstance(folders, tuple) else folders)


def cosmos_folders(config: Mapping[str, Any]) -> list[Path]:
    """The catalogue folders of ``simulation.sources.folder`` (one name or a list),
    under ``data.resources_dir``."""
    folder = config["simulation"]["sources"]["folder"]
    names = folder if isinstance(folder, (list, tuple)) else [folder]
    return [Path(config["data"]["resources_dir"]) / f for f in names]


def _cleaning(src: Mapping[str, Any]) -> tuple | None:
    """``(threshold, smoothing, dilate, taper, denoise, wavelet, denoise_smoothing)`` of
    ``simulation.sources.clean``, or None when cleaning is off."""
    c = src.get("clean") or {}
    if not c.get("enabled", False):
        return None
    return (
        float(c["threshold"]),
        float(c["smoothing"]),
        int(c["dilate"]),
        float(c["taper"]),
        str(c.get("denoise", "none")),
        str(c.get("denoise_wavelet", "db2")),
        float(c.get("denoise_smoothing", 1.0)),
    )


def _footprint(folders, ident: int, cleaning: tuple):
    cat = catalog_at(folders)
    t, s, d, tp = cleaning[:4]
    return clean_stamp(
        cat.stamp(ident), cat.noise_sigma(ident), threshold=t, smoothing=s, dilate=d, taper=tp
    )


@functools.lru_cache(maxsize=4096)
def _clean(folders, ident: int, cleaning: tuple) -> np.ndarray:
    cs = _footprint(folders, ident, cleaning)
    if cleaning[4] == "wavelet":
        cat = catalog_at(folders)
        out = denoise_stamp(
            cat.stamp(ident), cat.noise_sigma(ident), wavelet=cleaning[5], smoothing=cleaning[6]
        )
        out = out * cs.weight
    else:
        out = cs.image
    out.setflags(write=False)
    return out


@functools.lru_cache(maxsize=4096)
def _noise_ratio(folders, ident: int, cleaning: tuple | None) -> float:
    """Stamp noise left inside the footprint, in units of the stamp's σ (1: not denoised)."""
    if cleaning is None or cleaning[4] != "wavelet":
        return 1.0
    cat = catalog_at(folders)
    cs = _footprint(folders, ident, cleaning)
    return residual_noise_ratio(
        cat.stamp(ident),
        cat.noise_sigma(ident),
        cs.weight,
        wavelet=cleaning[5],
        smoothing=cleaning[6],
        seed=int(ident) % (2**32),
    )


def _folders_key(catalog: CosmosCatalog):
    folders = tuple(dict.fromkeys(str(f) for f in catalog.table["folder"]))
    return folders if len(folders) > 1 else folders[0]


def _stamp(catalog: CosmosCatalog, src: Mapping[str, Any], ident: int) -> np.ndarray:
    cleaning = _cleaning(src)
    if cleaning is None:
        return catalog.stamp(ident)
    return _clean(_folders_key(catalog), int(ident), cleaning)


def noise_fraction(
    catalog: CosmosCatalog,
    src: Mapping[str, Any],
    ident: int,
    zero_point: float,
    inst,
    psf_norm: float = 1.0,
) -> float:
    """Stamp noise of galaxy ``ident`` after placement at ``clean.reference_z_source`` and
    renormalisation to the brightest ``mag_renormalize`` magnitude (none: its own flux),
    as a fraction of the detector's background σ per pixel: ρ·σ_stamp·f·Δ²·‖PSF‖₂ / σ_det,
    with ρ the noise ratio left by the denoiser (1 without), ``f`` the factor placement
    and renormalisation multiply the stamp by, Δ the detector pixel (arcsec; a lensed
    pixel samples one source-plane point, so surface brightness noise becomes σ_sb·Δ² per
    pixel) and ‖PSF‖₂ = (Σ psf²)^½ the factor by which the PSF lowers white pixel noise
    (exact for white noise; the denoiser's residue is correlated, which the PSF lowers
    less)."""
    row = catalog.table.loc[catalog.table["ident"] == int(ident)].iloc[0]
    z_ref = float((src.get("clean") or {}).get("reference_z_source", 0.7))
    stamp = _stamp(catalog, src, ident)
    sb, pix = place_at_redshift(
        stamp, float(row["pixel_scale"]), float(row["zphot"]), z_ref, zero_point_out=zero_point
    )
    renorm = src.get("mag_renormalize")
    if renorm:
        sb = normalize_to_magnitude(sb, pix, float(min(renorm)), zero_point)
    peak = int(np.argmax(np.abs(stamp)))
    factor = float(sb.flat[peak] / stamp.flat[peak]) if stamp.flat[peak] != 0 else 0.0
    ratio = _noise_ratio(_folders_key(catalog), int(ident), _cleaning(src))
    sigma_sb = catalog.noise_sigma(ident) * ratio * factor
    return float(sigma_sb * inst.pixel_scale**2 * psf_norm / inst.background_sigma)


def brightest_magnitude(fraction: float, src: Mapping[str, Any]) -> float:
    """The brightest renormalised magnitude at which a galaxy with noise fraction
    ``fraction`` (at the brightest ``mag_renormalize`` magnitude, :func:`noise_fraction`)
    meets ``clean.max_noise_fraction``: the noise scales with the flux, so
    m = m_bright + 2.5 log10(fraction / limit) when over the limit (m_bright otherwise);
    NaN without renormalisation or limit."""
    renorm = src.get("mag_renormalize")
    limit = (src.get("clean") or {}).get("max_noise_fraction")
    if not renorm or limit is None:
        return float("nan")
    bright = float(min(renorm))
    if fraction <= limit:
        return bright
    return bright + 2.5 * float(np.log10(fraction / float(limit)))


def source_table(config: Mapping[str, Any]) -> pd.DataFrame:
    """Every galaxy of the configured catalogues with its cuts (:data:`SOURCE_COLUMNS`):
    the stamp's peak S/N and footprint, the noise ratio the denoiser leaves, the noise
    fraction, the brightest magnitude it may be drawn at, ``selected`` and ``split``."""
    src = config["simulation"]["sources"]
    inst, zp, psf_norm = _noise_model(config)
    cat = catalog_at(_key(cosmos_folders(config)))
    c = src.get("clean") or {}
    cleaning = _cleaning(src)
    rows = []
    for ident in cat.idents:
        cs = clean_stamp(
            cat.stamp(ident),
            cat.noise_sigma(ident),
            threshold=float(c.get("threshold", 3.0)),
            smoothing=float(c.get("smoothing", 1.0)),
            dilate=int(c.get("dilate", 2)),
            taper=float(c.get("taper", 2.0)),
        )
        frac = noise_fraction(cat, src, ident, zp, inst, psf_norm)
        rows.append(
            {
                "ident": int(ident),
                "peak_snr": cs.peak_snr,
                "footprint_fraction": cs.footprint_fraction,
                "noise_ratio": _noise_ratio(_folders_key(cat), int(ident), cleaning),
                "noise_fraction": frac,
                "brightest_mag": brightest_magnitude(frac, src),
            }
        )
    table = cat.table[["ident", "folder", "mag_auto", "zphot", "nx", "ny"]].merge(
        pd.DataFrame(rows), on="ident"
    )
    split_of = {}
    for name in ("train", "validation", "test"):
        try:
            _, ids = source_split(config, name)
        except ValueError:
            continue
        split_of.update({int(i): name for i in ids})
    table["selected"] = table["ident"].isin(list(split_of))
    table["split"] = table["ident"].map(split_of).fillna("")
    return table[list(SOURCE_COLUMNS)]


def _key(folders: Sequence[Path]):
    names = tuple(str(f) for f in folders)
    return names if len(names) > 1 else names[0]


def source_split(config: Mapping[str, Any], split: str) -> tuple[CosmosCatalog, np.ndarray]:
    """The COSMOS catalogue (after cuts) and the IDENTs of ``split``."""
    src = config["simulation"]["sources"]
    catalog = catalog_at(_key(cosmos_folders(config)))
    c = src["cuts"]
    selected = catalog.select(
        CosmosCuts(
            c["mag_max"],
            c["min_stamp_side"],
            c["min_flux_radius"],
            c["zphot_max"],
            tuple(c.get("exclude", ())),
        )
    )
    limit = (src.get("clean") or {}).get("max_noise_fraction")
    if _cleaning(src) is not None and limit is not None:
        selected = _noise_cut(config, selected, float(limit))
    s = src["split"]
    if s.get("ids"):
        ids = np.asarray(s["ids"].get(split, []), dtype=np.int64)
        missing = ids[~np.isin(ids, selected.idents)]
        if missing.size:
            raise ValueError(
                f"config key simulation.sources.split.ids.{split}: IDENT(s) {missing.tolist()} "
                "are not among the selected COSMOS galaxies"
            )
    else:
        ids = split_idents(
            selected.idents, {k: s[k] for k in ("train", "validation", "test")}, s["salt"]
        )[split]
    if ids.size == 0:
        raise ValueError(f"the COSMOS split {split!r} is empty (simulation.sources.split)")
    return selected, ids


def _noise_model(config):
    """Instrument, zero point and PSF norm (Σ psf²)^½ of the config."""
    from subslope.simulation.observing import build_instrument, build_psf

    psf = build_psf(config)
    return (
        build_instrument(config),
        float(config["instrument"]["zero_point"]),
        float(np.sqrt(np.sum(np.asarray(psf, dtype=np.float64) ** 2))),
    )


@functools.lru_cache(maxsize=16)
def _noise_fractions(config_json: str) -> dict[int, float]:
    import json

    config = json.loads(config_json)
    src = config["simulation"]["sources"]
    inst, zp, psf_norm = _noise_model(config)
    cat = catalog_at(_key(cosmos_folders(config)))
    return {int(i): noise_fraction(cat, src, i, zp, inst, psf_norm) for i in cat.idents}


def _fractions(config) -> dict[int, float]:
    from subslope.config import canonical_json

    keys = ("data", "instrument", "simulation")
    return _noise_fractions(canonical_json({k: config[k] for k in keys}))


def _dims(src: Mapping[str, Any]) -> bool:
    c = src.get("clean") or {}
    return c.get("noisy", "drop") == "dim" and bool(src.get("mag_renormalize"))


def _noise_cut(config, selected: CosmosCatalog, limit: float) -> CosmosCatalog:
    src = config["simulation"]["sources"]
    fracs = _fractions(config)
    frac = np.array([fracs[int(i)] for i in selected.idents])
    if _dims(src):
        faint = float(max(src["mag_renormalize"]))
        need = float((src.get("clean") or {}).get("min_magnitude_range", 0.5))
        bright = np.array([brightest_magnitude(f, src) for f in frac])
        ok = bright <= faint - need
    else:
        ok = frac <= limit
    keep = selected.idents[ok]
    dropped = selected.idents[~ok]
    log.info(
        "COSMOS noise cut (stamp noise <= %g x detector noise, %s): %d of %d galaxies kept; "
        "dropped %s",
        limit,
        "dimmed where needed" if _dims(src) else "dropped above",
        keep.size,
        frac.size,
        dropped.tolist()[:20],
    )
    if keep.size == 0:
        raise ValueError(
            f"no COSMOS galaxy keeps its stamp noise below simulation.sources.clean."
            f"max_noise_fraction = {limit} of the detector noise (fractions "
            f"{frac.min():.2f}–{frac.max():.2f}); raise it or renormalise to fainter magnitudes"
        )
    return selected.subset(keep)


def place_source(
    catalog: CosmosCatalog,
    src: Mapping[str, Any],
    ident: int,
    z_source: float,
    zero_point: float,
    mag: float | None,
):
    """Galaxy ``ident`` (cleaned as ``src['clean']`` says) at ``z_source``, renormalised to
    ``mag`` when given: ``(surface brightness, pixel scale, z_phot)``."""
    row = catalog.table.loc[catalog.table["ident"] == int(ident)].iloc[0]
    sb, pix = place_at_redshift(
        _stamp(catalog, src, ident),
        float(row["pixel_scale"]),
        float(row["zphot"]),
        float(z_source),
        zero_point_out=zero_point,
    )
    if mag is not None and np.isfinite(mag):
        sb = normalize_to_magnitude(sb, pix, float(mag), zero_point)
    return sb, pix, float(row["zphot"])


def pixelated_sources(stamps: Sequence[np.ndarray], pixel_scales, pad_shape, settings):
    """PixelatedSources padded to the fixed ``pad_shape`` (so an image does not depend on
    which other stamps share its batch)."""
    from subslope.render.pipeline import PixelatedSources

    filler = np.zeros(tuple(int(v) for v in pad_shape))
    padded, offsets = pad_stamps(list(stamps) + [filler], dtype=settings.dtype, device="cpu")
    return PixelatedSources(
        stamps=padded[:-1],
        offsets=offsets[:-1],
        pixel_scale=np.asarray(pixel_scales, dtype=np.float64),
    )


def landing_stamps(stamps: Sequence[np.ndarray]) -> list[np.ndarray]:
    """The support of each source stamp: 1 over the stamp's whole box, whatever its
    pixels hold. Lensed and PSF-convolved, it marks where the stamp lands in the image:
    the candidate pixels of ``placement: landing``. The reference code placed its CDM
    subhalos on the pixels where its lensed, undenoised COSMOS stamp was positive
    (repository gemyxzhang/neural-subhalo-slope-data, ``utils.py``), about half of the
    stamp's landing area by sky noise plus the galaxy; a uniform pick over the whole
    landing area has the same footprint (docs/simulation.md, "Subhalo placement")."""
    return [np.ones_like(np.asarray(s, dtype=np.float64)) for s in stamps]


def draw_sources(
    config: Mapping[str, Any],
    sc,
    macro: Mapping[str, np.ndarray],
    rng: np.random.Generator,
    zero_point: float,
) -> tuple[dict[str, np.ndarray], list[np.ndarray], tuple[int, int] | None]:
    """One COSMOS galaxy per image (uniform over the scene's split), placed at its
    z_source and renormalised (``mag_renormalize``; a dimmed galaxy from its own
    brightest magnitude): ``(per-image source records, stamps, padded stamp shape)``;
    nothing for a parametric source."""
    n = len(macro["z_source"])
    if sc.source.kind != "cosmos":
        return {}, [], None
    src = config["simulation"]["sources"]
    catalog, ids = source_split(config, sc.source.split)
    pick = ids[rng.integers(0, ids.size, n)]
    renorm = src["mag_renormalize"]
    mags = None
    if renorm:
        lo, hi = float(renorm[0]), float(renorm[1])
        if _dims(src):  # each galaxy from its own brightest magnitude (module docstring)
            fracs = _fractions(config)
            bright = {int(i): brightest_magnitude(fracs[int(i)], src) for i in ids}
            lo = np.array([max(lo, bright[int(i)]) for i in pick])
        mags = lo + (hi - lo) * rng.uniform(0.0, 1.0, n)
    pix = np.empty(n)
    zphot = np.empty(n)
    stamps = []
    for i in range(n):
        sb, pix[i], zphot[i] = place_source(
            catalog,
            src,
            pick[i],
            macro["z_source"][i],
            zero_point,
            None if mags is None else mags[i],
        )
        stamps.append(sb)
    pad_shape = (int(catalog.table["ny"].max()), int(catalog.table["nx"].max()))
    sources = {"ident": pick.astype(np.int64), "z_phot": zphot, "pixel_scale": pix}
    if mags is not None:
        sources["mag"] = mags
    return sources, stamps, pad_shape


def cleaning_examples(config: Mapping[str, Any], n: int = 4):
    """``(ident, raw, footprint only, cleaned, σ)`` of ``n`` galaxies of the configured
    catalogues spread over the stamp S/N (for :func:`subslope.figures.domain.source_cleaning`);
    ``cleaned`` is the stamp the simulations use (denoised in its footprint when
    ``clean.denoise`` is on)."""
    src = config["simulation"]["sources"]
    cleaning = _cleaning(src) or (3.0, 1.0, 2, 2.0, "wavelet", "db2", 1.0)
    cat = catalog_at(_key(cosmos_folders(config)))
    folders = _folders_key(cat)
    snr = np.array([cat.stamp(i).max() / cat.noise_sigma(i) for i in cat.idents])
    order = np.argsort(snr)
    picks = order[np.linspace(0, order.size - 1, min(n, order.size)).round().astype(int)]
    out = []
    for k in picks:
        ident = int(cat.idents[k])
        raw = cat.stamp(ident)
        foot = _footprint(folders, ident, cleaning).image
        out.append((ident, raw, foot, _clean(folders, ident, cleaning), cat.noise_sigma(ident)))
    return out
