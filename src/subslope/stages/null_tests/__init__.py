"""Stage ``null_tests``: what the estimator reads where there is no γ to read.

The stage has three parts, one module each: the null scenes (this module, rule
null_tests), images re-rendered without their substructure (:mod:`.halo_free`, rules
halo_free_profiles and halo_free_null) and the CDM sets re-rendered without their
subhalos (:mod:`.visibility`, rules subhalo_free_profiles and cdm_visibility);
docs/inference.md.

The null scenes are scenes in which the label γ cannot be seen (no subhalos, with and
without line-of-sight halos) pushed through the same inference as the test sets.

An estimator that reads γ from the subhalos returns flat profiles there: its γ_MLE
spreads over the whole prior, its mean ln r̂(γ) is flat, and a calibrated interval
covers the whole prior. One that reads γ from anything else (the arc's position, the
source, the lens light) gives curved profiles and intervals that exclude part of the
prior. The table holds, for every null scene, the spread of the single-image and stack
γ_MLE, the range of the mean profile and the fractions of intervals that exclude part of
the prior.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from subslope.figures.save import save_figure
from subslope.io.atomic import write_text
from subslope.io.ratio_profiles import read_profiles
from subslope.stages.calibrate import load_thresholds, set_stacks, threshold_for
from subslope.stats import intervals

__all__ = ["NULL_COLUMNS", "null_scene_row", "null_tests"]

log = logging.getLogger(__name__)

#: Columns of ``null_tests.csv``, one row per null scene.
NULL_COLUMNS = (
    "scene",
    "n_images",
    "n_stacks",
    "single_mle_p16",
    "single_mle_p50",
    "single_mle_p84",
    "stack_mle_p16",
    "stack_mle_p50",
    "stack_mle_p84",
    "mean_profile_range",
    "single_excluding",
    "stack_excluding",
    "tau_1",
    "tau_n",
    "n_per_stack",
)


def _excluding(profiles, gammas, tau: float) -> float:
    """Fraction of the profiles whose interval at ``tau`` excludes part of the prior."""
    ivs = intervals.intervals(profiles, gammas, tau)
    return float(np.mean([not (iv.lower_at_edge and iv.upper_at_edge) for iv in ivs]))


def null_scene_row(
    data: Mapping[str, np.ndarray], thresholds: Mapping[str, Any], scene: str
) -> tuple[dict[str, Any], np.ndarray, dict[str, np.ndarray]]:
    """The table row of one null scene (its profiles ``data`` as
    :func:`subslope.io.ratio_profiles.read_profiles` returns them), the mean single-image
    ln r̂ minus its maximum ``(G,)``, and the single and stack γ_MLE for the figure."""
    g = data["gammas"]
    lr = np.asarray(data["log_ratio"], dtype=np.float64)
    single_mle = np.atleast_1d(intervals.mle(lr, g))
    st = set_stacks(data)
    n_per = int(np.median(st["n_images"]))
    tau_1, _ = threshold_for(thresholds, 1)
    tau_n, _ = threshold_for(thresholds, n_per)
    mean = lr.mean(axis=0)
    p = np.percentile
    row = {
        "scene": scene,
        "n_images": int(lr.shape[0]),
        "n_stacks": int(st["mle"].size),
        "single_mle_p16": float(p(single_mle, 16)),
        "single_mle_p50": float(p(single_mle, 50)),
        "single_mle_p84": float(p(single_mle, 84)),
        "stack_mle_p16": float(p(st["mle"], 16)),
        "stack_mle_p50": float(p(st["mle"], 50)),
        "stack_mle_p84": float(p(st["mle"], 84)),
        "mean_profile_range": float(np.ptp(mean)),
        "single_excluding": _excluding(lr, g, tau_1),
        "stack_excluding": _excluding(st["profiles"], g, tau_n),
        "tau_1": float(tau_1),
        "tau_n": float(tau_n),
        "n_per_stack": n_per,
    }
    return row, mean - mean.max(), {"single": single_mle, "stack": st["mle"]}


def null_tests(
    profile_paths: Mapping[str, Sequence],
    thresholds_json,
    out_csv,
    fig_stem,
    *,
    run_name: str,
    source: str | None = None,
):
    """Table ``null_tests.csv`` (:data:`NULL_COLUMNS`) and figure of the null scenes:
    ``profile_paths`` maps each null scene to its profiles files."""
    import pandas as pd

    from subslope.figures.null_tests import null_test_figure

    thr = load_thresholds(thresholds_json)
    rows, means, mles, gammas = [], {}, {}, None
    for scene, paths in profile_paths.items():
        data = read_profiles(list(paths))
        row, means[scene], mles[scene] = null_scene_row(data, thr, scene)
        gammas = data["gammas"]
        rows.append(row)
        log.info("null scene %s: %s", scene, row)
    table = pd.DataFrame(rows, columns=NULL_COLUMNS)
    write_text(out_csv, table.to_csv(index=False))
    fig = null_test_figure(gammas, means, mles, table, run_name=run_name, source=source)
    save_figure(fig, fig_stem, run_name=run_name)
    return table
