"""Stage ``hst``: profiles, intervals and figures 5–6 of the real HST lenses (rule
analyze_hst)."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from subslope.figures.save import save_figure
from subslope.io.atomic import atomic_write, write_text
from subslope.io.observations import find_lens_centre
from subslope.nre.evaluate import log_ratio_profiles
from subslope.physics.instrument import PIXEL_SCALE
from subslope.stages.calibrate import load_thresholds, threshold_for
from subslope.stages.cdm_grid import cdm_band
from subslope.stats import calibration, intervals

__all__ = ["analyze_hst"]


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
    highlight: Sequence[str] = ("SDSSJ0946+1006",),
    lens_centre: Mapping[str, Any] | None = None,
    pixel_scale: float = PIXEL_SCALE,
    batch_size: int = 16,
    device: str = "auto",
    nfw_scene: str = "nfw",
    tnfw_scene: str | None = "tnfw",
):
    """Profiles, intervals and figures 5–6 of the real HST lenses.

    Every cutout goes through the same pre-processing as the simulations (training
    whitening, 1.5 θ_E mask) with θ_E from the catalogue and the lens centre measured by
    :func:`find_lens_centre`. Individual intervals use τ_1; the combined stack of the
    ``combine`` systems (default all) uses τ_N, N = their number. Writes ``out_h5``
    (names, log_ratio, gammas, theta_e, lens_x, lens_y, combined), ``out_csv`` (one row per
    system and one ``combined`` row: mle, lower, upper, threshold, threshold_n, flags) and
    the figures; the a = 1 NFW/tNFW bands of figure 6 come from ``cdm_csv`` when given.
    """
    import pandas as pd

    from subslope.figures.paper import hst_combined, hst_profiles
    from subslope.io.observations import load_hst
    from subslope.nre.train import load_estimator

    obs = load_hst(hst_folder)
    names = [o.name for o in obs]
    combine = list(names) if combine is None else list(combine)
    unknown = sorted((set(combine) | set(show) | set(highlight)) - set(names))
    if unknown:
        raise ValueError(f"hst: unknown system(s) {unknown}; catalogued: {names}")
    centres = [
        find_lens_centre(o.image, pixel_scale=pixel_scale, **dict(lens_centre or {})) for o in obs
    ]
    images = np.stack([o.image for o in obs]).astype(np.float32)
    theta_e = np.array([o.theta_e for o in obs])
    lx, ly = np.array([c[0] for c in centres]), np.array([c[1] for c in centres])
    model, meta = load_estimator(model_path)
    prep = meta.get("preprocess", {})
    prof = log_ratio_profiles(
        model,
        images,
        theta_e,
        lx,
        ly,
        meta["whitening"],
        gammas,
        batch_size=batch_size,
        device=None if device in (None, "auto") else device,
        pixel_scale=prep.get("pixel_scale", pixel_scale),
        mask_factor=prep.get("mask_factor", 1.5),
    )
    g = np.asarray(gammas, dtype=np.float64)
    thr = load_thresholds(thresholds_json)
    tau1, n1 = threshold_for(thr, 1)
    rows = []
    for k, name in enumerate(names):
        iv = intervals.interval(prof[k], g, tau1)
        rows.append(
            {
                "system": name,
                "n_images": 1,
                "threshold_n": n1,
                "lens_x": lx[k],
                "lens_y": ly[k],
                "theta_e": theta_e[k],
                **iv.as_dict(),
            }
        )
    idx = [names.index(s) for s in combine]
    combined = intervals.stack(prof[idx])
    tau_c, n_c = threshold_for(thr, len(idx))
    iv_c = intervals.interval(combined, g, tau_c)
    rows.append(
        {
            "system": "combined",
            "n_images": len(idx),
            "threshold_n": n_c,
            "lens_x": np.nan,
            "lens_y": np.nan,
            "theta_e": np.nan,
            **iv_c.as_dict(),
        }
    )
    table = pd.DataFrame(rows)
    write_text(out_csv, table.to_csv(index=False))
    out_h5 = Path(out_h5)
    with atomic_write(out_h5) as tmp, h5py.File(tmp, "w") as fh:
        fh.create_dataset("names", data=np.array(names, dtype="S"))
        fh.create_dataset("log_ratio", data=prof)
        fh.create_dataset("gammas", data=g)
        fh.create_dataset("theta_e", data=theta_e)
        fh.create_dataset("lens_x", data=lx)
        fh.create_dataset("lens_y", data=ly)
        fh.create_dataset("combined", data=combined)
        fh.create_dataset("combined_systems", data=np.array(combine, dtype="S"))
        fh.attrs["run_name"] = run_name
        fh.attrs["model"] = os.fspath(model_path)
    source = f"estimator {meta.get('config_hash', '')}"
    shown = {s: prof[names.index(s)] for s in (show or names)}
    fig5 = hst_profiles(
        g,
        shown,
        tau1,
        run_name=run_name,
        source=source,
        kind="log_ratio",
        wilks=calibration.wilks_threshold(thr.get("level", 0.68)),
        highlight=tuple(highlight),
    )
    save_figure(fig5, fig5_stem, run_name=run_name)
    cdm = pd.read_csv(cdm_csv) if cdm_csv else None
    bn = cdm_band(cdm, nfw_scene)
    bt = cdm_band(cdm, tnfw_scene) if tnfw_scene else None
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
        n_images=len(idx),
    )
    save_figure(fig6, fig6_stem, run_name=run_name)
    return table
