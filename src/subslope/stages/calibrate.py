"""Stage ``calibrate``: the threshold τ_N per stack size and its held-out coverage
(rules calibrate_threshold, summarize_coverage), and the readers of the thresholds
that the later stages use."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from subslope.figures.save import save_figure
from subslope.io.atomic import atomic_write, read_json, write_json, write_text
from subslope.io.ratio_profiles import read_profiles
from subslope.plan import derived_seed
from subslope.stats import calibration, intervals

__all__ = [
    "calibrate_stack_size",
    "summarize_coverage",
    "load_thresholds",
    "threshold_for",
    "set_stacks",
    "COVERAGE_COLUMNS",
]

log = logging.getLogger(__name__)


def calibrate_stack_size(
    profile_paths,
    n: int,
    out_npz,
    *,
    level: float = 0.68,
    seed: int = 0,
    heldout_fraction: float = 0.5,
    levels=None,
    stacks: str = "independent",
) -> dict[str, Any]:
    """Threshold τ_N and held-out coverage for stacks of ``n`` images; writes ``out_npz``.

    Stacks: :func:`subslope.stats.calibration.make_stacks` with ``mode=stacks``
    (``independent``: the first N images of every set, one stack per set;
    ``disjoint``: seeded disjoint N-subsets of every set of images sharing γ). Split by
    set (:func:`subslope.stats.calibration.split`): ``heldout_fraction`` of the sets are
    held out. ``tau`` uses all stacks (the threshold
    for new data), ``tau_calibration`` the calibration part only, whose held-out coverage
    is reported (with Wilks' χ²₁ threshold for comparison) along with expected-coverage
    curves over ``levels`` (default 0.01…0.99).

    The npz holds: n, level, tau, tau_exact, tau_calibration, tau_wilks, t_true, gamma,
    set_id, is_calibration, indices, levels, coverage_curve, coverage_curve_wilks, and the
    scalars of the coverage (coverage, coverage_err, wilson_lo, wilson_hi, coverage_wilks,
    coverage_wilks_err, n_calibration, n_heldout). Returns the same as a dict.
    """
    data = read_profiles(profile_paths)
    ok = np.isfinite(data["gamma_true"])
    if not ok.all():
        raise ValueError(
            f"calibration needs labelled images; {int((~ok).sum())} have no gamma_true"
        )
    rng = np.random.default_rng(derived_seed(seed, f"stacks/N{int(n)}"))
    cut = calibration.make_stacks(data["gamma_true"], data["set_id"], int(n), rng, mode=stacks)
    t_true = calibration.stack_t_true(data["log_ratio"], data["gammas"], cut)
    cal = calibration.calibrate(
        t_true,
        cut.set_id,
        level=level,
        seed=derived_seed(seed, "split"),
        fraction=1.0 - heldout_fraction,
        levels=levels,
    )
    out = dict(
        n=int(n),
        level=float(level),
        t_true=t_true,
        gamma=cut.gamma,
        set_id=cut.set_id,
        indices=cut.indices,
        **cal,
    )
    tau, exact, cov = cal["tau"], cal["tau_exact"], cal
    out_npz = Path(out_npz)
    with atomic_write(out_npz) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **out)
    log.info(
        "N=%d: %d stacks, tau=%.4g (exact %s), held-out coverage %.3f (Wilks %.3f)",
        n,
        len(cut),
        tau,
        exact,
        cov["coverage"],
        cov["coverage_wilks"],
    )
    return out


#: Columns of ``coverage.csv``: the stack size, the number of stacks, the calibration
#: table's columns (:data:`subslope.stats.calibration.CALIBRATION_COLUMNS`) with the
#: coverage's distance from its level in standard errors, the level and the verdict.
_WILSON = calibration.CALIBRATION_COLUMNS.index("wilson_lo")
COVERAGE_COLUMNS = (
    "n_images",
    "n_stacks",
    *calibration.CALIBRATION_COLUMNS[:_WILSON],
    "coverage_sigma",
    *calibration.CALIBRATION_COLUMNS[_WILSON:],
    "level",
    "overconfident",
)


def summarize_coverage(
    npz_paths, out_csv, out_json, fig_stem, *, run_name: str, source: str | None = None
):
    """Table of every N (``calibration.csv``), the thresholds (``thresholds.json``:
    ``{"level", "tau": {N: τ_N}, "exact": {N: bool}, "wilks"}``) and the coverage figure."""
    import pandas as pd

    from subslope.figures.paper import coverage_figure

    rows, curves, curves_w = [], {}, {}
    levels = None
    for p in npz_paths:
        with np.load(p) as z:
            n = int(z["n"])
            sigma = calibration.coverage_sigma(z["level"], z["n_calibration"], z["n_heldout"])
            rows.append(
                {
                    "n_images": n,
                    "n_stacks": int(z["t_true"].size),
                    "tau": float(z["tau"]),
                    "tau_exact": bool(z["tau_exact"]),
                    "tau_wilks": float(z["tau_wilks"]),
                    "tau_calibration": float(z["tau_calibration"]),
                    "n_calibration": int(z["n_calibration"]),
                    "n_heldout": int(z["n_heldout"]),
                    "coverage": float(z["coverage"]),
                    "coverage_err": float(z["coverage_err"]),
                    "coverage_sigma": float(sigma),
                    "wilson_lo": float(z["wilson_lo"]),
                    "wilson_hi": float(z["wilson_hi"]),
                    "coverage_wilks": float(z["coverage_wilks"]),
                    "coverage_wilks_err": float(z["coverage_wilks_err"]),
                    "level": float(z["level"]),
                    "overconfident": bool(
                        calibration.overconfident(z["coverage"], sigma, z["level"])
                    ),
                }
            )
            levels = z["levels"]
            curves[n], curves_w[n] = z["coverage_curve"], z["coverage_curve_wilks"]
    table = (
        pd.DataFrame(rows, columns=COVERAGE_COLUMNS).sort_values("n_images").reset_index(drop=True)
    )
    write_text(out_csv, table.to_csv(index=False))
    thr = {
        "level": float(table["level"].iloc[0]),
        "wilks": float(table["tau_wilks"].iloc[0]),
        "tau": {str(int(r.n_images)): float(r.tau) for r in table.itertuples()},
        "exact": {str(int(r.n_images)): bool(r.tau_exact) for r in table.itertuples()},
    }
    write_json(out_json, thr)
    plot_table = table.fillna({"coverage": np.nan})
    fig = coverage_figure(
        plot_table,
        levels,
        {k: np.nan_to_num(v, nan=0.0) for k, v in sorted(curves.items())},
        {k: np.nan_to_num(v, nan=0.0) for k, v in sorted(curves_w.items())},
        run_name=run_name,
        source=source,
    )
    save_figure(fig, fig_stem, run_name=run_name)
    return table, thr


def load_thresholds(path) -> dict[str, Any]:
    """``thresholds.json`` of :func:`summarize_coverage` with integer N keys."""
    thr = read_json(path)
    thr["tau"] = {int(k): float(v) for k, v in thr["tau"].items()}
    thr["exact"] = {int(k): bool(v) for k, v in thr.get("exact", {}).items()}
    return thr


def threshold_for(thresholds: Mapping[str, Any], n: int) -> tuple[float, int]:
    """``(τ, N used)``: τ_N if N was calibrated, else the largest calibrated N below it
    (logged as a warning: the interval is then not calibrated for this stack size)."""
    taus = thresholds["tau"]
    if n in taus:
        return taus[n], n
    below = [k for k in taus if k <= n] or list(taus)
    k = max(below) if any(k <= n for k in taus) else min(taus)
    log.warning(
        "no threshold calibrated for N=%d; using tau_%d (the interval is not calibrated)", n, k
    )
    return taus[k], k


def set_stacks(data: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """One stack per set (all images sharing γ): stacked profiles ``(S, G)``, ``mle (S,)``,
    ``gamma_true (S,)``, ``c_multiplier (S,)``, ``n_images (S,)``."""
    ids, inv = np.unique(data["set_id"], return_inverse=True)
    stacked = intervals.stack(data["log_ratio"], inv)
    first = np.array([np.flatnonzero(inv == k)[0] for k in range(ids.size)], dtype=np.int64)
    return {
        "profiles": stacked,
        "mle": np.atleast_1d(intervals.mle(stacked, data["gammas"])),
        "gamma_true": data["gamma_true"][first],
        "c_multiplier": data["c_multiplier"][first],
        "n_images": np.bincount(inv, minlength=ids.size),
    }
