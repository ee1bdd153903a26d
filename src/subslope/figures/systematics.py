"""The systematics figure: the HST slope, the CDM predictions and the calibration of
every simulator variant side by side (:mod:`subslope.campaigns.systematics`)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from subslope.figures.save import footer

__all__ = ["systematics_figure"]


def systematics_figure(rows: Sequence[Mapping[str, Any]], *, level: float, run_name: str) -> Figure:
    """Left: per variant (one line each), the combined HST γ_MLE with its calibrated
    interval (black; an open side drawn as an arrow), and the a = 1 NFW (blue) and tNFW
    (green) stack γ_MLE medians with their 16–84% bands. Right: held-out coverage at
    N = 1 and at the largest N with binomial errors, against the level."""
    n = len(rows)
    fig = Figure(figsize=(9.5, 1.2 + 0.45 * max(n, 1)))
    ax1, ax2 = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.6, 1.0]}, sharey=True)
    y = np.arange(n)[::-1].astype(float)
    for yi, r in zip(y, rows):
        for prefix, color, dy in (("nfw", "tab:blue", 0.18), ("tnfw", "tab:green", -0.18)):
            med = r[f"{prefix}_median"]
            if not math.isnan(med):
                lo, hi = r[f"{prefix}_p16"], r[f"{prefix}_p84"]
                ax1.errorbar(
                    med, yi + dy, xerr=[[med - lo], [hi - med]], fmt="s", ms=4,
                    color=color, lw=1.2, capsize=2,
                )  # fmt: skip
        mle, lo, hi = r["hst_gamma_mle"], r["hst_lower"], r["hst_upper"]
        ax1.errorbar(mle, yi, xerr=[[mle - lo], [hi - mle]], fmt="o", color="k", lw=1.8, capsize=3)
        for side, edge, sign in (("lower", lo, -1), ("upper", hi, 1)):
            if side in str(r["hst_open"]):
                ax1.annotate(
                    "", xy=(edge + sign * 0.12, yi), xytext=(edge, yi),
                    arrowprops={"arrowstyle": "->", "color": "k", "lw": 1.2},
                )  # fmt: skip
        for key, dy, marker in (("n1", 0.12, "o"), ("nmax", -0.12, "D")):
            ax2.errorbar(
                r[f"coverage_{key}"], yi + dy, xerr=r[f"coverage_{key}_err"],
                fmt=marker, ms=4, color="tab:red" if key == "n1" else "tab:purple", capsize=2,
            )  # fmt: skip
    ax1.plot([], [], "ko-", label="HST combined γ_MLE, calibrated 68% interval")
    ax1.plot([], [], "s-", color="tab:blue", label="NFW a = 1 (16–84%)")
    ax1.plot([], [], "s-", color="tab:green", label="tNFW a = 1 (16–84%)")
    ax1.set_yticks(y, [str(r["variant"]) for r in rows])
    ax1.set_xlabel(r"$\gamma$")
    ax1.grid(alpha=0.25, axis="x")
    ax1.legend(fontsize=6.5, frameon=False, loc="lower left", bbox_to_anchor=(0, 1.0))
    ax2.axvline(level, color="0.4", ls="--", lw=0.9)
    ax2.plot([], [], "o", color="tab:red", label="coverage N = 1")
    n_max = rows[0]["n_max"] if rows else 13
    ax2.plot([], [], "D", color="tab:purple", label=f"coverage N = {n_max}")
    ax2.set_xlabel(f"held-out coverage (level {level:.2f})")
    ax2.set_xlim(0, 1)
    ax2.grid(alpha=0.25, axis="x")
    ax2.legend(fontsize=6.5, frameon=False, loc="lower left", bbox_to_anchor=(0, 1.0))
    footer(fig, run_name, "systematics.csv")
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    return fig
