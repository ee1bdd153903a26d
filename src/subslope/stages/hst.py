"""Stage ``hst``: profiles, intervals and figures 5–6 of the real HST lenses (rule
analyze_hst)."""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from subslope.figures.save import save_figure
from subslope.io.atomic import atomic_write, write_text
from subslope.io.observations import find_lens_centre
from subslope.nre.evaluate import estimator_profiles
from subslope.physics.instrument import PIXEL_SCALE
from subslope.stages.calibrate import load_thresholds, threshold_for
from subslope.stages.cdm_grid import cdm_band
from subslope.stats import calibration, intervals

__all__ = ["leave_one_out", "analyze_hst", "hst_profiles"]

log = logging.getLogger(__name__)


def analyze_hst(
    model_path,
    hst_folder,
    thresholds_json,
    out_h5,
    out_csv,
    fig5_stem,
    fig6_stem,
    *,
    run_name: str,
    gammas,
    cdm_csv=None,
    combine: Sequence[str] | None = None,
    show: Sequence[str] = (),
    highlight: Sequence[str] = (),
    lens_centre: Mapping[str, Any] | None = None,
    pixel_scale: float = PIXEL_SCALE,
    batch_size: int = 16,
    device: str = "auto",
    nfw_scene: str = "nfw",
    tnfw_scene: str | None = "tnfw",
    reference_scenes: Sequence | None = None,
    domain_csv=None,
    config: Mapping[str, Any] | None = None,
    loo_csv=None,
):
    """Profiles (:func:`hst_profiles`), intervals (τ_1; the stack of ``combine``, default
    all, τ_N) and figures 5–6 of the real HST lenses: ``out_h5`` (names, log_ratio,
    gammas, theta_e, lens_x, lens_y, combined), ``out_csv`` (a row per system and a
    ``combined`` row; ``inside_domain`` from ``domain_csv``), the figures (figure 6's
    a = 1 bands from ``cdm_csv``), ``loo_csv`` (:func:`leave_one_out`)."""
    import pandas as pd

    names, geometry, prof, meta = hst_profiles(
        model_path,
        hst_folder,
        gammas,
        lens_centre=lens_centre,
        pixel_scale=pixel_scale,
        batch_size=batch_size,
        device=device,
        config=config,
    )
    combine = _known_systems(names, combine, show, highlight)
    g = np.asarray(gammas, dtype=np.float64)
    thr = load_thresholds(thresholds_json)
    tau1, n1 = threshold_for(thr, 1)
    rows = [
        _row(name, prof[k], g, tau1, 1, n1, {key: v[k] for key, v in geometry.items()})
        for k, name in enumerate(names)
    ]
    idx = [names.index(s) for s in combine]
    combined = intervals.stack(prof[idx])
    tau_c, n_c = threshold_for(thr, len(idx))
    iv_c = intervals.interval(combined, g, tau_c)
    rows.append(
        _row("combined", combined, g, tau_c, len(idx), n_c, dict.fromkeys(geometry, np.nan))
    )
    table = _with_domain_flags(pd.DataFrame(rows), domain_csv)
    write_text(out_csv, table.to_csv(index=False))
    _write_leave_one_out(loo_csv, [names[k] for k in idx], prof[idx], g, thr)
    _write_h5(out_h5, names, prof, g, geometry, combined, combine, run_name, model_path)
    source = f"estimator {meta.get('config_hash', '')}"
    shown = {s: prof[names.index(s)] for s in (show or names)}
    _figures(
        g,
        shown,
        combined,
        iv_c,
        (tau1, tau_c),
        thr,
        (fig5_stem, fig6_stem),
        cdm_csv,
        (nfw_scene, tnfw_scene, *(reference_scenes or (None, None))),
        run_name=run_name,
        source=source,
        highlight=tuple(highlight),
        n_images=len(idx),
    )
    return table


def hst_profiles(
    model_path,
    hst_folder,
    gammas,
    *,
    lens_centre: Mapping[str, Any] | None = None,
    pixel_scale: float = PIXEL_SCALE,
    batch_size: int = 16,
    device: str = "auto",
    config: Mapping[str, Any] | None = None,
):
    """ln r̂ of the HST cutouts on ``gammas`` with the estimator's own pre-processing:
    its input transform (lens light fitted as in the shards, ``config``'s PSF and
    detector), whitening and 1.5 θ_E mask (θ_E catalogued, centre of
    :func:`find_lens_centre`).

    Returns ``(names, geometry, log_ratio, meta)``: the catalogue's system names, their
    ``lens_x, lens_y`` (arcsec, :func:`find_lens_centre`) and catalogued ``theta_e``,
    the ``(systems, len(gammas))`` profiles and the estimator's metadata. ``config`` (PSF
    and detector of the lens-light fit) is needed by estimators whose inputs subtract
    the fitted lens light.
    """
    names, theta_e, lx, ly, images = _lenses(hst_folder, pixel_scale, lens_centre)
    prof, meta = _profiles(
        model_path, (images, theta_e, lx, ly), gammas, batch_size, device, pixel_scale, config
    )
    return names, {"lens_x": lx, "lens_y": ly, "theta_e": theta_e}, prof, meta


def _known_systems(names, combine, show, highlight) -> list[str]:
    """The systems to stack (``combine``, default all), after checking that every system
    named in ``combine``, ``show`` and ``highlight`` is catalogued."""
    combine = list(names) if combine is None else list(combine)
    unknown = sorted((set(combine) | set(show) | set(highlight)) - set(names))
    if unknown:
        raise ValueError(f"hst: unknown system(s) {unknown}; catalogued: {names}")
    return combine


def _with_domain_flags(table, domain_csv):
    """``table`` with the domain check's ``inside`` / ``outside`` per system (the
    combined row: inside when every stacked system is)."""
    import pandas as pd

    if not domain_csv:
        return table
    dom = pd.read_csv(domain_csv, keep_default_na=False)
    inside = dict(zip(dom["system"], dom["inside"].astype(str).str.lower() == "true", strict=True))
    outside = dict(zip(dom["system"], dom["outside"], strict=True))
    table = table.copy()
    table["inside_domain"] = [inside.get(s, False) for s in table["system"]]
    table["outside_domain"] = [outside.get(s, "") for s in table["system"]]
    singles = table["system"] != "combined"
    table.loc[~singles, "inside_domain"] = bool(table.loc[singles, "inside_domain"].all())
    return table


def _lenses(hst_folder, pixel_scale: float, lens_centre: Mapping[str, Any] | None):
    """Names, Einstein radii, measured lens centres and images of the HST cutouts."""
    from subslope.io.observations import load_hst

    obs = load_hst(hst_folder)
    centres = [
        find_lens_centre(o.image, pixel_scale=pixel_scale, **dict(lens_centre or {})) for o in obs
    ]
    theta_e = np.array([o.theta_e for o in obs])
    lx, ly = np.array([c[0] for c in centres]), np.array([c[1] for c in centres])
    return (
        [o.name for o in obs],
        theta_e,
        lx,
        ly,
        np.stack([o.image for o in obs]).astype(np.float32),
    )


def _write_leave_one_out(path, systems, profiles, g, thr) -> None:
    import pandas as pd

    if path is None:
        return
    tau, n = threshold_for(thr, max(len(systems) - 1, 1))
    write_text(path, pd.DataFrame(leave_one_out(systems, profiles, g, tau, n)).to_csv(index=False))


def leave_one_out(systems: Sequence[str], profiles, g, tau: float, threshold_n: int) -> list[dict]:
    """The combined stack of ``profiles`` (one row per system of ``systems``) with each
    system left out in turn: its γ_MLE and interval at ``tau`` (the threshold of stacks
    one image smaller, calibrated for ``threshold_n`` images), and the shift of γ_MLE
    against the stack of all of them. A lens whose removal moves the combined γ_MLE by
    more than the others carries the result."""
    prof = np.asarray(profiles, dtype=np.float64)
    full = intervals.interval(intervals.stack(prof), g, tau).as_dict()["mle"]
    rows = []
    for k, system in enumerate(systems):
        rest = np.delete(prof, k, axis=0)
        iv = intervals.interval(intervals.stack(rest), g, tau).as_dict()
        rows.append(
            {
                "left_out": system,
                "n_images": len(rest),
                "threshold_n": threshold_n,
                "mle": iv["mle"],
                "lower": iv["lower"],
                "upper": iv["upper"],
                "shift": iv["mle"] - full,
            }
        )
    return rows


def _row(
    system: str, profile, g, tau: float, n_images: int, threshold_n: int, geometry
) -> dict[str, Any]:
    """One row of intervals.csv: the interval of ``profile`` at ``tau``."""
    iv = intervals.interval(profile, g, tau)
    return {
        "system": system,
        "n_images": n_images,
        "threshold_n": threshold_n,
        **geometry,
        **iv.as_dict(),
    }


def _profiles(model_path, lenses, gammas, batch_size, device, pixel_scale, config):
    """ln r̂ of the cutouts with the estimator's own pre-processing, and its metadata."""
    from subslope.nre.inputs import InputTransform
    from subslope.nre.train import load_estimator

    images, theta_e, lx, ly = lenses
    model, meta = load_estimator(model_path)
    light = None
    if InputTransform.from_json(meta.get("inputs")).needs_light:
        light = _light_models(config, images, theta_e)
    prof = estimator_profiles(
        model,
        meta,
        images,
        theta_e,
        lx,
        ly,
        gammas,
        batch_size=batch_size,
        device=device,
        pixel_scale=pixel_scale,
        light=light,
    )
    return prof, meta


def _light_models(config, images, theta_e) -> np.ndarray:
    """The lens light of the cutouts, fitted with the code and settings of the shards."""
    if config is None:
        raise ValueError(
            "the estimator subtracts the fitted lens light: analyze_hst needs the workflow "
            "config (PSF and detector of the fit)"
        )
    from subslope.simulation.observing import fitted_light_models

    fit, light = fitted_light_models(config, images, theta_e)
    log.info("lens light of the cutouts: chi2/dof %s", np.round(fit["chi2_dof"], 2).tolist())
    return light


def _write_h5(path, names, prof, g, geometry, combined, combine, run_name: str, model_path) -> None:
    """profiles.h5: names, ln r̂ (systems × grid), the grid, the lens geometry, the combined
    stack and its systems; the run name and estimator as attributes."""
    arrays = {
        "names": np.array(names, dtype="S"),
        "log_ratio": prof,
        "gammas": g,
        **geometry,
        "combined": combined,
        "combined_systems": np.array(combine, dtype="S"),
    }
    arrays = {
        k: arrays[k]
        for k in (
            "names",
            "log_ratio",
            "gammas",
            "theta_e",
            "lens_x",
            "lens_y",
            "combined",
            "combined_systems",
        )
    }
    with atomic_write(Path(path)) as tmp, h5py.File(tmp, "w") as fh:
        for key, value in arrays.items():
            checked = value.size > 0 and value.dtype.kind != "S"  # checksums on every number
            fh.create_dataset(key, data=value, fletcher32=checked, chunks=True if checked else None)
        fh.attrs["run_name"] = run_name
        fh.attrs["model"] = os.fspath(model_path)


def _figures(
    g,
    shown,
    combined,
    iv_c,
    taus,
    thr,
    stems,
    cdm_csv,
    scenes,
    *,
    run_name,
    source,
    highlight,
    n_images,
) -> None:
    """Figure 5 (every shown lens, τ_1) and figure 6 (the combined stack, τ_N, with the
    a = 1 CDM bands when the grid ran)."""
    import pandas as pd

    from subslope.figures.paper import hst_combined, hst_profiles

    tau1, tau_c = taus
    fig5 = hst_profiles(
        g,
        shown,
        tau1,
        run_name=run_name,
        source=source,
        kind="log_ratio",
        wilks=calibration.wilks_threshold(thr.get("level", 0.68)),
        highlight=highlight,
    )
    save_figure(fig5, stems[0], run_name=run_name)
    cdm = pd.read_csv(cdm_csv) if cdm_csv else None
    bn = cdm_band(cdm, scenes[0])
    bt = cdm_band(cdm, scenes[1]) if scenes[1] else None
    refs = [cdm_band(cdm, s) if s else None for s in scenes[2:4]]
    fig6 = hst_combined(
        g,
        combined,
        tau_c,
        None if bn is None else bn[1:],
        None if bt is None else bt[1:],
        interval=iv_c,
        run_name=run_name,
        source=source,
        kind="log_ratio",
        n_images=n_images,
        reference_bands=tuple(None if b is None else b[1:] for b in refs),
    )
    save_figure(fig6, stems[1], run_name=run_name)
