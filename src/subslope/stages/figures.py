"""Stage ``figures``: the training curves, figures 2 and 3 and the estimator trend
(rules plot_training_curves, plot_validation)."""

from __future__ import annotations

from typing import Any

import numpy as np

from subslope.figures.save import save_figure
from subslope.figures.training import plot_training_curves
from subslope.io.ratio_profiles import read_profiles
from subslope.stages.calibrate import load_thresholds, set_stacks, threshold_for
from subslope.stats import intervals

__all__ = ["plot_training_curves", "plot_validation", "spearman_trend"]


def plot_validation(
    single_paths,
    stack_paths,
    thresholds_json,
    fig2_stem,
    fig3_stem,
    *,
    run_name: str,
    source: str | None = None,
) -> dict[str, Any]:
    """Figure 2 (single images, τ_1) and figure 3 (whole sets of the stack scene, τ_N with
    N = images per set). Returns the Spearman trend of the stack MLEs (:func:`spearman_trend`)."""
    from subslope.figures.paper import stack_scatter, validation_scatter

    thr = load_thresholds(thresholds_json)
    single = read_profiles(single_paths)
    g = single["gammas"]
    tau1, _ = threshold_for(thr, 1)
    ivs = intervals.intervals(single["log_ratio"], g, tau1)
    fig2 = validation_scatter(
        single["gamma_true"],
        [i.mle for i in ivs],
        [i.lower for i in ivs],
        [i.upper for i in ivs],
        run_name=run_name,
        source=source,
        threshold=tau1,
        open_lower=[i.lower_at_edge for i in ivs],
        open_upper=[i.upper_at_edge for i in ivs],
        prior=(float(g[0]), float(g[-1])),
    )
    save_figure(fig2, fig2_stem, run_name=run_name)
    st = set_stacks(read_profiles(stack_paths))
    n = int(np.median(st["n_images"]))
    tau_n, _ = threshold_for(thr, n)
    ivs = intervals.intervals(st["profiles"], g, tau_n)
    fig3 = stack_scatter(
        st["gamma_true"],
        [i.mle for i in ivs],
        [i.lower for i in ivs],
        [i.upper for i in ivs],
        run_name=run_name,
        n_images=n,
        source=source,
        threshold=tau_n,
        open_lower=[i.lower_at_edge for i in ivs],
        open_upper=[i.upper_at_edge for i in ivs],
        prior=(float(g[0]), float(g[-1])),
    )
    save_figure(fig3, fig3_stem, run_name=run_name)
    return spearman_trend(st["gamma_true"], st["mle"])


def spearman_trend(gamma_true, mle) -> dict[str, float]:
    """Spearman rank correlation between true γ and the MLE: ``{rho, p_value, n}``."""
    from scipy import stats

    gt, m = np.asarray(gamma_true, dtype=np.float64), np.asarray(mle, dtype=np.float64)
    ok = np.isfinite(gt) & np.isfinite(m)
    if ok.sum() < 3 or np.ptp(m[ok]) == 0 or np.ptp(gt[ok]) == 0:
        return {"rho": float("nan"), "p_value": float("nan"), "n": int(ok.sum())}
    res = stats.spearmanr(gt[ok], m[ok])
    return {"rho": float(res.statistic), "p_value": float(res.pvalue), "n": int(ok.sum())}
