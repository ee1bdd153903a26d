"""Stage ``domain``: does the simulation look like the data? (rules fit_lens_light and
check_domain; ``subslope domain-check``).

- :func:`fit_hst_lens_light`: the PSF-convolved Sérsic fit of every HST lens's light
  (arcs masked, sky pedestal fitted) and the priors derived from the fits: the joint
  lens-light prior (:func:`subslope.physics.light.fit.joint_prior_from_fits`, beside the
  shipped ``hst_joint`` preset), the sky level and the old uniform boxes;
  :func:`fit_hst_lens_light_job` takes them from the cache (``simulation.shard_cache``)
  where a campaign (a systematics variant) already made them from the same files,
  settings and code (:func:`lens_light_fit_key`);
- :func:`check_domain`: the statistics of :mod:`subslope.validation.domain` over the first
  ``domain.n_images`` images of a scene's shards and over the 13 HST cutouts, each lens's
  percentile in the simulated distribution, the spread of every statistic (simulated
  1–99% against the HST range), the figures, and the COSMOS source table
  (per-galaxy peak S/N, footprint and noise fraction, selection);
- :func:`domain_check_cli`: the same check on images simulated in the process.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from subslope.config import config_hash
from subslope.figures.domain import domain_gallery, domain_histograms
from subslope.figures.save import save_figure
from subslope.io.atomic import write_text
from subslope.io.observations import find_lens_centre, load_hst
from subslope.io.shard_cache import (
    CODE_PARTS,
    code_digest,
    put_files_in_cache,
    take_files_from_cache,
)
from subslope.io.shards import file_sha256, open_shard
from subslope.physics.cosmology import arcsec_to_mpc
from subslope.physics.light.fit import (
    fit_lens_light,
    joint_prior_from_fits,
    prior_from_fits,
    sky_prior_from_fits,
)
from subslope.simulation.observing import build_instrument, build_psf
from subslope.validation.domain import (
    STATISTICS,
    border_level,
    domain_percentiles,
    image_statistics,
    spread_table,
)

__all__ = [
    "fit_hst_lens_light",
    "fit_hst_lens_light_job",
    "lens_light_fit_key",
    "LENS_LIGHT_FILES",
    "JOINT_WIDEN",
    "check_domain",
    "domain_check_cli",
    "shard_images",
]

log = logging.getLogger(__name__)

#: Factor on the standard deviations of the fits in the joint lens-light prior: the 13
#: fits are a small sample of the population, and every lens must stay inside the
#: domain check's 1–99% bounds.
JOINT_WIDEN = 1.5


def fit_hst_lens_light(config: Mapping[str, Any], hst_folder, out_csv, out_prior) -> pd.DataFrame:
    """Fit the lens light of every HST cutout; write the fits (one row per system, with
    the fitted sky pedestal ``sky``, the border level and R_s in kpc at z_lens) to
    ``out_csv`` and the derived priors, with the shipped ``hst_joint`` preset beside them,
    to ``out_prior`` (YAML)."""
    import yaml

    from subslope.simulation.presets import LENS_LIGHT_PRIORS

    psf, inst = build_psf(config), build_instrument(config)
    obs = load_hst(hst_folder)
    images = np.stack([o.image for o in obs])
    lc = dict(config["hst"]["lens_centre"])
    centres = np.array([find_lens_centre(o.image, pixel_scale=inst.pixel_scale, **lc) for o in obs])
    fit = fit_lens_light(
        images,
        psf,
        centres,
        np.array([o.theta_e for o in obs]),
        background_sigma=inst.background_sigma,
        exposure_time=inst.total_exposure_time,
        pixel_scale=inst.pixel_scale,
    )
    table = pd.DataFrame(
        {
            "system": [o.name for o in obs],
            "theta_e": [o.theta_e for o in obs],
            "mag": fit.mag,
            "r_sersic": fit.r_sersic,
            "n_sersic": fit.n_sersic,
            "e1": fit.e1,
            "e2": fit.e2,
            "q": fit.q,
            "x": fit.x,
            "y": fit.y,
            "chi2_dof": fit.chi2_dof,
            "used_fraction": fit.mask.mean((1, 2)),
            "cutout_mag": inst.magnitude_zero_point - 2.5 * np.log10(images.sum((1, 2))),
            "sky": fit.background,
            "border_level": border_level(images),
            "r_kpc": fit.r_sersic * 1e3 * arcsec_to_mpc(np.array([o.z_lens for o in obs])),
        }
    )
    write_text(out_csv, table.to_csv(index=False, float_format="%.6g"))
    joint = joint_prior_from_fits(fit.mag, fit.r_sersic, fit.n_sersic, fit.q, widen=JOINT_WIDEN)
    shipped = LENS_LIGHT_PRIORS["hst_joint"]["joint"]
    doc = {
        "derived_joint": joint,
        "shipped_hst_joint": shipped,
        "shipped_equals_derived": joint == shipped,
        "derived_sky": sky_prior_from_fits(fit.background, widen=JOINT_WIDEN),
        "derived_boxes": prior_from_fits(fit.mag, fit.r_sersic, fit.n_sersic, fit.q),
    }
    write_text(out_prior, yaml.safe_dump(doc, sort_keys=False))
    if not doc["shipped_equals_derived"]:
        log.warning(
            "the shipped hst_joint lens-light prior differs from the one derived now: %s", joint
        )
    return table


#: The files of a lens-light fit in the cache (kind ``lens_light``), by output.
LENS_LIGHT_FILES = {"csv": "lens_light_fits.csv", "prior": "lens_light_prior.yaml"}


def lens_light_fit_key(config: Mapping[str, Any], hst_folder: str | os.PathLike[str]) -> str:
    """Cache key of the HST lens-light fits: SHA-256 of what they depend on: the bytes
    of every file of ``hst_folder`` and of the PSF file, the ``instrument`` section, the
    lens-centre settings (``hst.lens_centre``) and the code that draws, reads and fits
    (:data:`subslope.io.shard_cache.CODE_PARTS` and this module)."""
    folder = Path(hst_folder)
    folder = folder.parent if folder.is_file() else folder  # a configured catalogue
    files = {p.name: file_sha256(p) for p in sorted(folder.iterdir()) if p.is_file()}
    psf = config["instrument"]["psf"]
    if psf["source"] != "gaussian":
        files["psf"] = file_sha256(Path(config["data"]["resources_dir"]) / psf["file"])
    return config_hash(
        {
            "files": files,
            "instrument": config["instrument"],
            "lens_centre": config["hst"]["lens_centre"],
            "code": code_digest((*CODE_PARTS, "stages/domain.py")),
        }
    )


def fit_hst_lens_light_job(
    config: Mapping[str, Any], hst_folder, out_csv, out_prior
) -> pd.DataFrame:
    """Rule fit_lens_light: :func:`fit_hst_lens_light`, or its files from the cache
    ``simulation.shard_cache`` (kind ``lens_light``) where they are there for
    :func:`lens_light_fit_key`; a new fit is put there. Returns the fits table."""
    cache = config["simulation"].get("shard_cache")
    outputs = {LENS_LIGHT_FILES["csv"]: out_csv, LENS_LIGHT_FILES["prior"]: out_prior}
    key = lens_light_fit_key(config, hst_folder) if cache else ""
    if cache and take_files_from_cache(cache, "lens_light", key, outputs):
        return pd.read_csv(out_csv)
    table = fit_hst_lens_light(config, hst_folder, out_csv, out_prior)
    if cache:
        put_files_in_cache(cache, "lens_light", key, outputs)
    return table


def shard_images(paths: Sequence[str | os.PathLike[str]], n: int):
    """The first ``n`` images of the shards ``paths`` (in order) and their θ_E."""
    images, theta_e = [], []
    have = 0
    for path in paths:
        if have >= n:
            break
        with open_shard(path) as shard:
            k = min(len(shard), n - have)
            images.append(np.asarray(shard.images[:k], dtype=np.float64))
            theta_e.append(np.asarray(shard.params["theta_e"][:k], dtype=np.float64))
            have += k
    if have == 0:
        raise ValueError(f"no images in the shards {list(paths)}")
    if have < n:
        log.warning("domain check: only %d images in the shards (asked for %d)", have, n)
    return np.concatenate(images), np.concatenate(theta_e)


def check_domain(
    config: Mapping[str, Any],
    images,
    theta_e,
    whitening: tuple[float, float],
    hst_folder,
    out_dir,
    figure_stems: Sequence[str],
    *,
    scene: str,
    inputs=None,
) -> pd.DataFrame:
    """Statistics of the simulated ``images`` and the HST cutouts; writes
    ``domain_check.csv`` (one row per HST system: each statistic's percentile,
    ``inside``, ``outside``), ``statistics.csv`` (every image's statistics, ``kind`` sim
    or hst), ``spread.csv`` (:func:`subslope.validation.domain.spread_table`) and
    ``sources.csv`` (the COSMOS galaxies) to ``out_dir`` and the figures: the histograms,
    the gallery and, with a third stem and COSMOS sources, the cleaned stamps. The
    whitened statistics are taken after ``inputs`` (default: the config's input transform,
    :func:`subslope.stages.train.input_transform`), as the estimator sees the images."""
    from subslope.stages.train import input_transform

    out_dir = Path(out_dir)
    dom = config["domain"]
    psf, inst = build_psf(config), build_instrument(config)
    kw = {
        "psf": psf,
        "background_sigma": inst.background_sigma,
        "exposure_time": inst.total_exposure_time,
        "whitening": whitening,
        "pixel_scale": inst.pixel_scale,
        "mask_factor": config["training"]["mask_factor"],
        "lens_centre": dict(config["hst"]["lens_centre"]),
        "inputs": input_transform(config) if inputs is None else inputs,
    }
    log.info("domain check: statistics of %d %s images", len(images), scene)
    sim = image_statistics(images, theta_e, **kw)
    obs = load_hst(hst_folder)
    names = [o.name for o in obs]
    real_images = np.stack([o.image for o in obs])
    real = image_statistics(real_images, [o.theta_e for o in obs], **kw)
    table = domain_percentiles(sim, real, names, bounds=tuple(dom["bounds"]))
    write_text(out_dir / "domain_check.csv", table.to_csv(index=False, float_format="%.4g"))
    both = pd.concat(
        [sim.assign(kind="sim", system=""), real.assign(kind="hst", system=names)],
        ignore_index=True,
    )
    write_text(out_dir / "statistics.csv", both.to_csv(index=False, float_format="%.6g"))
    spread = spread_table(sim, real, bounds=tuple(dom["bounds"]))
    write_text(out_dir / "spread.csv", spread.to_csv(index=False, float_format="%.4g"))
    _write_sources(config, out_dir / "sources.csv", scene)
    run = config["run_name"]
    save_figure(
        domain_histograms(sim, real, table, STATISTICS, run_name=run, scene=scene),
        figure_stems[0],
        run_name=run,
    )
    save_figure(
        domain_gallery(real_images, names, images, run_name=run, scene=scene),
        figure_stems[1],
        run_name=run,
    )
    if len(figure_stems) > 2:
        _source_figure(config, scene, figure_stems[2])
    log.info("domain check: %d of %d HST lenses inside", int(table["inside"].sum()), len(table))
    return table


def _source_figure(config: Mapping[str, Any], scene: str, stem: str) -> None:
    """The COSMOS stamps before and after cleaning (an empty note for parametric sources)."""
    from matplotlib.figure import Figure

    from subslope.figures.domain import source_cleaning
    from subslope.simulation.resolve import resolved_scene
    from subslope.simulation.sources import cleaning_examples

    run = config["run_name"]
    if resolved_scene(config, scene)[0].source.kind == "cosmos":
        fig = source_cleaning(cleaning_examples(config), run_name=run)
    else:
        fig = Figure(figsize=(4, 1))
        fig.text(0.5, 0.5, f"scene {scene} draws parametric sources", ha="center")
    save_figure(fig, stem, run_name=run)


def _write_sources(config: Mapping[str, Any], path: Path, scene: str) -> None:
    """The COSMOS source table (:func:`subslope.simulation.sources.source_table`); only
    its header when ``scene`` draws parametric sources."""
    from subslope.simulation.resolve import resolved_scene
    from subslope.simulation.sources import SOURCE_COLUMNS, source_table

    if resolved_scene(config, scene)[0].source.kind == "cosmos":
        table = source_table(config)
    else:
        table = pd.DataFrame(columns=list(SOURCE_COLUMNS))
    write_text(path, table.to_csv(index=False, float_format="%.4g"))


def domain_check_cli(
    config: Mapping[str, Any], scene: str, n: int, out, *, whitening_json=None, seed=None
) -> pd.DataFrame:
    """:func:`check_domain` on ``n`` images of ``scene`` simulated here (seed: the
    config's), whitened with ``whitening_json`` or, without one, with the pixel mean and
    std of those images; outputs under ``out`` (``domain_check.csv`` and the figures)."""
    from subslope.nre.preprocess import read_whitening
    from subslope.simulation.shard import shard_seed_sequence, simulate_images

    ss = shard_seed_sequence(int(config["seed"] if seed is None else seed), scene, 0, 0)
    sim = simulate_images(config, scene, int(n), ss)
    images = np.asarray(sim["images"], dtype=np.float64)
    theta_e = np.asarray(sim["params"]["theta_e"], dtype=np.float64)
    from subslope.nre.inputs import InputTransform

    inputs = None  # the config's transform, with the whitening measured after it
    if whitening_json is not None:
        white = read_whitening(whitening_json)
    else:
        white, inputs = (float(images.mean()), float(images.std())), InputTransform()
    cfg = dict(config)
    cfg["domain"] = dict(config["domain"], scene=scene)
    out = Path(out)
    return check_domain(
        cfg,
        images,
        theta_e,
        white,
        Path(config["data"]["resources_dir"]) / "hst",
        out,
        (str(out / "domain_check"), str(out / "domain_gallery"), str(out / "source_cleaning")),
        scene=scene,
        inputs=inputs,
    )
