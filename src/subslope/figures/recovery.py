"""Figures 2 and 3: how well the slope is recovered, γ_MLE and its 68% interval against
the true γ, for single images and for stacks (docs/inference.md).

Hundreds of error bars on top of each other hide what a reader wants to see, so the
figures show bins of true γ: the median γ_MLE with its 16–84% band, and the medians of
the interval's lower and upper bounds with their own bands. The individual estimates
are drawn faint behind (hollow where the interval is open at a prior edge).
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from subslope.figures.save import footer

__all__ = ["binned_quantiles", "stack_scatter", "validation_scatter"]

#: Quantiles drawn per bin: the 16–84% band and the median.
QUANTILES = (0.16, 0.5, 0.84)


def binned_quantiles(x, y, edges, quantiles=QUANTILES, *, min_count: int = 3):
    """Quantiles of ``y`` in bins of ``x``.

    Returns ``(centres (B,), q (B, len(quantiles)), counts (B,))`` for the bins
    ``[edges[i], edges[i+1])`` (the last one closed); bins with fewer than ``min_count``
    points get NaN quantiles.
    """
    x, y = np.asarray(x, dtype=np.float64).ravel(), np.asarray(y, dtype=np.float64).ravel()
    edges = np.asarray(edges, dtype=np.float64)
    if x.shape != y.shape:
        raise ValueError(f"x and y must have the same length, got {x.size} and {y.size}")
    if edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0):
        raise ValueError("edges must be an increasing 1-D array of at least 2 values")
    which = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, edges.size - 2)
    inside = (x >= edges[0]) & (x <= edges[-1]) & np.isfinite(y)
    q = np.full((edges.size - 1, len(quantiles)), np.nan)
    counts = np.zeros(edges.size - 1, dtype=np.int64)
    for b in range(edges.size - 1):
        sel = inside & (which == b)
        counts[b] = int(sel.sum())
        if counts[b] >= min_count:
            q[b] = np.quantile(y[sel], quantiles)
    return 0.5 * (edges[:-1] + edges[1:]), q, counts


def _open(flags, n: int) -> np.ndarray:
    return np.zeros(n, bool) if flags is None else np.asarray(flags, bool).ravel()


def _recovery_axes(ax, gamma_true, mle, lo, hi, open_any, prior, color, label, n_bins):
    """Faint estimates, binned bands of γ_MLE and of the bounds, the 1:1 line."""
    ax.plot(prior, prior, color="0.4", lw=1, ls="--", zorder=1, label="1:1")
    closed = ~open_any
    dot = {"s": 6, "linewidths": 0.5, "zorder": 2}
    ax.scatter(gamma_true[closed], mle[closed], color=color, alpha=0.25, **dot, label=label)
    if open_any.any():
        ax.scatter(
            gamma_true[open_any],
            mle[open_any],
            facecolors="none",
            edgecolors="0.5",
            alpha=0.4,
            **dot,
            label="interval open at a prior edge",
        )
    edges = np.linspace(prior[0], prior[1], n_bins + 1)
    centres, q_mle, _ = binned_quantiles(gamma_true, mle, edges)
    _, q_lo, _ = binned_quantiles(gamma_true, lo, edges)
    _, q_hi, _ = binned_quantiles(gamma_true, hi, edges)
    ax.fill_between(centres, q_mle[:, 0], q_mle[:, 2], color=color, alpha=0.3, lw=0, zorder=3)
    ax.plot(
        centres,
        q_mle[:, 1],
        color=color,
        lw=2,
        zorder=4,
        label=r"median $\gamma_\mathrm{MLE}$, 16–84%",
    )
    for q in (q_lo, q_hi):
        ax.fill_between(centres, q[:, 0], q[:, 2], color="0.5", alpha=0.12, lw=0, zorder=3)
        ax.plot(centres, q[:, 1], color="0.25", lw=1, ls=":", zorder=4)
    ax.plot([], [], color="0.25", lw=1, ls=":", label="median 68% bounds, 16–84%")
    pad = 0.02 * (prior[1] - prior[0])
    ax.set_xlim(prior[0] - pad, prior[1] + pad)
    ax.set_ylim(prior[0] - pad, prior[1] + pad)
    ax.set_aspect("equal")
    ax.set_xlabel(r"true $\gamma$")
    ax.set_ylabel(r"$\gamma_\mathrm{MLE}$ and its 68% interval")
    ax.grid(alpha=0.25)
    ax.legend(loc="upper left", fontsize=7, frameon=False)
    return float(np.mean((lo <= gamma_true) & (gamma_true <= hi)))


def _recovery_figure(
    gamma_true,
    mle,
    lo,
    hi,
    *,
    title: str,
    color: str,
    unit: str,
    run_name: str,
    source: str | None = None,
    gamma_range: tuple[float, float] | None = None,
    open_lower=None,
    open_upper=None,
    prior: tuple[float, float] = (1.1, 2.9),
    threshold: float | None = None,
    n_bins: int = 12,
) -> Figure:
    arrays = [np.asarray(a, dtype=np.float64).ravel() for a in (gamma_true, mle, lo, hi)]
    for a, name in zip(arrays, ("gamma_true", "mle", "lo", "hi"), strict=True):
        if a.size != arrays[0].size:
            raise ValueError(f"{name} must have {arrays[0].size} values like gamma_true")
    if arrays[0].size == 0:
        raise ValueError("gamma_true is empty: nothing to plot")
    keep = np.ones(arrays[0].size, bool)
    if gamma_range is not None:
        keep = (arrays[0] > gamma_range[0]) & (arrays[0] < gamma_range[1])
        if not keep.any():
            raise ValueError(f"no point with {gamma_range[0]} < gamma_true < {gamma_range[1]}")
    g, m, lo_, hi_ = (a[keep] for a in arrays)
    n = arrays[0].size
    open_any = (_open(open_lower, n) | _open(open_upper, n))[keep]
    fig = Figure(figsize=(4.6, 4.9))
    ax = fig.subplots()
    cov = _recovery_axes(ax, g, m, lo_, hi_, open_any, prior, color, f"{keep.sum()} {unit}", n_bins)
    txt = f"{cov:.0%} of intervals contain the true $\\gamma$"
    if threshold is not None:
        txt += f"\nthreshold $\\tau$ = {threshold:.3g}"
    ax.text(0.97, 0.03, txt, transform=ax.transAxes, ha="right", va="bottom", fontsize=7)
    extra = None if gamma_range is None else f"{gamma_range[0]} < true γ < {gamma_range[1]}"
    footer(fig, run_name, source, extra)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.035, 1, 0.95))
    return fig


def validation_scatter(
    gamma_true, mle, lo, hi, *, gamma_range=(1.2, 2.8), n_bins: int = 12, **kwargs
) -> Figure:
    """Fig. 2: single-image γ_MLE and its 68% interval ``[lo, hi]`` against the true γ, in
    ``n_bins`` bins of true γ (median and 16–84% of each), estimates faint behind.

    Only images with ``gamma_range[0] < γ_true < gamma_range[1]`` are drawn (``None``:
    all). The corner text gives the fraction of intervals containing γ_true. Keyword
    arguments: ``run_name`` (required), ``source``, ``open_lower``/``open_upper`` (flags
    of intervals at a prior edge), ``prior``, ``threshold``.
    """
    return _recovery_figure(
        gamma_true,
        mle,
        lo,
        hi,
        title="Single images: maximum-likelihood slope vs truth",
        color="#1f5fa8",
        unit="images",
        gamma_range=gamma_range,
        n_bins=n_bins,
        **kwargs,
    )


def stack_scatter(
    gamma_true, mle, lo, hi, *, n_images: int = 13, n_bins: int = 8, **kwargs
) -> Figure:
    """Fig. 3: γ_MLE and its 68% interval of stacks of ``n_images`` EPL images against their
    shared true γ, binned as in :func:`validation_scatter` (same keyword arguments; all
    stacks drawn unless ``gamma_range`` is given)."""
    return _recovery_figure(
        gamma_true,
        mle,
        lo,
        hi,
        title=f"Stacks of {n_images} EPL images: maximum-likelihood slope vs truth",
        color="#c2185b",
        unit=f"stacks of {n_images}",
        n_bins=n_bins,
        **kwargs,
    )
