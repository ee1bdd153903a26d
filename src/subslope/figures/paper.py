"""Result figures: the paper's figures 2–6 and the coverage check (docs/inference.md).

Every function takes plain arrays (computed by :mod:`subslope.stats.intervals` and
:mod:`subslope.stats.calibration`), builds a matplotlib :class:`~matplotlib.figure.Figure`
without pyplot (so it works under any backend, Agg included, and touches no global
state) and returns it; :func:`save` writes it as PDF and PNG atomically. Each figure
names, in a footer, the run it came from (``run_name``) and optionally a ``source``
string (e.g. the estimator file or config hash). docs/inference.md says how to read them.

| function | paper | shows |
|---|---|---|
| :func:`validation_scatter` | Fig. 2 | single images: binned γ_MLE and 68% bounds vs true γ |
| :func:`stack_scatter` | Fig. 3 | 13-image EPL stacks, the same against their shared γ |
| :func:`concentration_grid` | Fig. 4 | stack MLEs (median, 16–84%) vs concentration multiplier a |
| :func:`hst_profiles` | Fig. 5 | t(γ) of individual HST systems with the single-image threshold |
| :func:`hst_combined` | Fig. 6 | combined HST t(γ), its 68% interval, the a = 1 NFW/tNFW bands |
| :func:`coverage_figure` | — | held-out coverage per N and expected-coverage curves |
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib import colormaps
from matplotlib.figure import Figure
from matplotlib.ticker import NullLocator

from subslope.figures.recovery import stack_scatter, validation_scatter
from subslope.figures.save import footer
from subslope.stats.intervals import Interval, test_statistic

__all__ = [
    "concentration_grid",
    "coverage_figure",
    "hst_combined",
    "hst_profiles",
    "stack_scatter",
    "validation_scatter",
]

GAMMA_LABEL = r"$\gamma$"
C_HST = "#c2185b"  # magenta: HST data
C_NFW = "#1f77b4"  # blue: NFW
C_TNFW = "#2ca02c"  # green: tNFW


# ---------------------------------------------------------------------------------------
# shared helpers
# ---------------------------------------------------------------------------------------
def _finish(fig: Figure, title: str | None = None) -> Figure:
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.035, 1, 0.95 if title else 1))
    return fig


# ---------------------------------------------------------------------------------------
# Fig. 4
# ---------------------------------------------------------------------------------------
def concentration_grid(
    multipliers,
    mles_nfw,
    mles_tnfw=None,
    *,
    run_name: str,
    source: str | None = None,
    n_images: int = 13,
    cdm: float = 1.0,
    hst: tuple[float, float, float] | None = None,
    percentiles: tuple[float, float, float] = (16, 50, 84),
    reference_nfw=None,
    reference_tnfw=None,
    controls: Sequence[tuple[float, float]] = (),
    second: Mapping | None = None,
    titles: tuple[str, str] = (
        "(t)NFW subhalos over the whole field",
        "the reference code's sets: where the source lands",
    ),
) -> Figure:
    """Fig. 4: stack MLEs against the concentration multiplier ``a`` (log axis).

    ``reference_nfw``/``reference_tnfw``: optional ``(3, n_a)`` rows (lo, median, hi) of
    the sets' effective subhalo slopes (:mod:`subslope.physics.effective_slope`), drawn as
    a line with a band: what each point would read if the estimator read the slope the
    images resolve.

    ``mles_nfw``/``mles_tnfw``: ``(n_a, n_sets)`` MLEs of the ``n_sets`` stacks of
    ``n_images`` at each multiplier (NaN entries are ignored). Points: median; bars: the
    16–84% range of the stack MLEs (the spread of the measurement from one set of 13
    lenses to another). ``a = cdm`` (1) is marked as the CDM prediction. ``hst``:
    optional ``(mle, lo, hi)`` of the real stack, drawn as a horizontal band.
    ``controls``: ``(γ, median)`` of the matched EPL controls (what a power-law
    population of slope γ reads on the same sets), drawn as dotted lines. ``second``: a
    second grid on the same multipliers (keys ``mles_nfw``, ``mles_tnfw``,
    ``reference_nfw``, ``reference_tnfw``, ``controls``), drawn as a panel to the right
    on a shared γ axis; ``titles`` name the two panels.
    """
    a = np.asarray(multipliers, dtype=np.float64).ravel()
    if a.size == 0 or np.any(a <= 0):
        raise ValueError("multipliers must be a non-empty array of positive values (log axis)")
    panels = [
        {
            "mles_nfw": mles_nfw,
            "mles_tnfw": mles_tnfw,
            "reference_nfw": reference_nfw,
            "reference_tnfw": reference_tnfw,
            "controls": controls,
        }
    ]
    if second is not None:
        panels.append(dict(second))
    fig = Figure(figsize=(5.6 * len(panels), 4.8))
    axes = np.atleast_1d(fig.subplots(1, len(panels), sharey=True))
    for k, (ax, panel) in enumerate(zip(axes, panels)):
        _grid_panel(ax, a, panel, hst, cdm, percentiles)
        if len(panels) > 1:
            ax.set_title(titles[k], fontsize=9)
    axes[0].set_ylabel(rf"stack $\gamma_\mathrm{{MLE}}$ ({n_images} images)")
    footer(fig, run_name, source)
    return _finish(fig, f"Slope measured on {n_images}-image stacks of (t)NFW subhalo simulations")


def _grid_panel(ax, a, panel: Mapping, hst, cdm: float, percentiles) -> None:
    """One panel of :func:`concentration_grid`: the NFW/tNFW stack MLEs per multiplier,
    the effective-slope references, the HST band and the CDM marker."""
    series = [("NFW subhalos", panel["mles_nfw"], C_NFW, "o", 1 / 1.03)]
    if panel.get("mles_tnfw") is not None:
        series.append(("tNFW subhalos", panel["mles_tnfw"], C_TNFW, "s", 1.03))
    for label, key, color in (("NFW", "reference_nfw", C_NFW), ("tNFW", "reference_tnfw", C_TNFW)):
        if panel.get(key) is not None:
            _draw_reference(ax, a, panel[key], label, color)
    for k, (gamma, median) in enumerate(panel.get("controls") or ()):
        ax.axhline(
            median,
            color="0.45",
            ls=":",
            lw=1.0,
            label="matched EPL controls (median)" if k == 0 else None,
        )
        ax.text(
            1.0,
            median,
            f" EPL γ = {gamma:g}",
            transform=ax.get_yaxis_transform(),
            ha="left",
            va="center",
            fontsize=7,
            color="0.35",
        )
    for label, m, color, marker, shift in series:
        m = np.asarray(m, dtype=np.float64)
        if m.ndim != 2 or m.shape[0] != a.size:
            raise ValueError(f"{label}: MLEs must have shape (n_a={a.size}, n_sets), got {m.shape}")
        lo, med, hi = np.nanpercentile(m, percentiles, axis=1)
        ax.errorbar(
            a * shift,
            med,
            yerr=[med - lo, hi - med],
            fmt=marker,
            color=color,
            ms=5,
            capsize=2.5,
            label=f"{label} (median, {percentiles[0]:g}–{percentiles[2]:g}% "
            f"of {m.shape[1]} stacks)",
        )
    if hst is not None:
        h_mle, h_lo, h_hi = hst
        ax.axhspan(h_lo, h_hi, color=C_HST, alpha=0.15, lw=0)
        ax.axhline(h_mle, color=C_HST, lw=1, label=f"HST stack: {h_mle:.2f} (68%)")
    ax.axvline(cdm, color="0.3", ls=":", lw=1.2)
    ax.text(
        cdm,
        0.02,
        f" CDM prediction ($a$ = {cdm:g})",
        transform=ax.get_xaxis_transform(),
        ha="left",
        va="bottom",
        fontsize=8,
        color="0.2",
    )
    ax.set_xscale("log")
    ax.set_xticks(a, [f"{v:g}" for v in a])
    ax.xaxis.set_minor_locator(NullLocator())
    ax.set_xlim(a.min() / 1.25, a.max() * 1.25)
    ax.set_xlabel(r"concentration multiplier $a$ ($c_{200} = a\,c_\mathrm{CDM}$)")
    ax.grid(alpha=0.25)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.16), fontsize=7, frameon=False)


def _draw_reference(ax, a, ref, label: str, color) -> None:
    """The sets' effective slopes ``ref`` (rows lo, median, hi) as a dashed line and band."""
    ref = np.asarray(ref, dtype=np.float64)
    if ref.shape != (3, a.size):
        raise ValueError(f"{label} reference must have shape (3, {a.size}), got {ref.shape}")
    ax.fill_between(a, ref[0], ref[2], color=color, alpha=0.12, lw=0)
    ax.plot(
        a, ref[1], color=color, ls="--", lw=1.2, marker="_", ms=14,
        label=f"{label} effective slope of the sets (median, 16–84%)",
    )  # fmt: skip


# ---------------------------------------------------------------------------------------
# Fig. 5 and 6
# ---------------------------------------------------------------------------------------
def _to_t(profile, gammas, kind):
    if kind == "t":
        return np.asarray(profile, dtype=np.float64)
    if kind == "log_ratio":
        return test_statistic(profile, gammas)
    raise ValueError(f"kind must be 't' or 'log_ratio', got {kind!r}")


def _draw_bands(ax, bands):
    for label, (lo, hi), color in bands:
        ax.axvspan(lo, hi, color=color, alpha=0.18, lw=0, label=label)


def hst_profiles(
    gammas,
    profiles: Mapping[str, np.ndarray],
    threshold: float,
    *,
    run_name: str,
    source: str | None = None,
    kind: str = "t",
    wilks: float | None = None,
    highlight: Sequence[str] = (),
    ymax: float | None = None,
) -> Figure:
    """Fig. 5: test-statistic profiles t(γ) of individual HST systems.

    ``profiles``: system name → ``t(γ)`` (``kind='t'``) or ``ln r̂(γ)`` (``kind='log_ratio'``,
    converted with :func:`subslope.stats.intervals.test_statistic`). The horizontal line is the
    single-image threshold τ₁ (a system's 68% interval is where its curve lies below it);
    ``wilks`` adds the χ²₁ value for comparison. Systems named in ``highlight`` are drawn
    thicker.
    """
    g = np.asarray(gammas, dtype=np.float64)
    if not profiles:
        raise ValueError("hst_profiles: no profiles to plot")
    ts = {name: _to_t(p, g, kind) for name, p in profiles.items()}
    fig = Figure(figsize=(6.4, 4.4))
    ax = fig.subplots()
    cmap = colormaps["tab10" if len(ts) <= 10 else "tab20"]
    for k, (name, t) in enumerate(ts.items()):
        hl = name in highlight
        ax.plot(
            g,
            t,
            color=cmap(k % cmap.N),
            lw=2.4 if hl else 1.1,
            label=name + (" ★" if hl else ""),
            zorder=3 if hl else 2,
        )
    ax.axhline(
        threshold, color="k", ls="--", lw=1, label=rf"68% threshold $\tau_1$ = {threshold:.3g}"
    )
    if wilks is not None:
        ax.axhline(wilks, color="0.5", ls=":", lw=1, label=rf"Wilks $\chi^2_1$: {wilks:.3g}")
    top = (
        ymax
        if ymax is not None
        else max(3 * threshold, min(max(float(t.max()) for t in ts.values()), 12 * threshold))
    )
    ax.set_ylim(0, top * 1.03)
    ax.set_xlim(g[0], g[-1])
    ax.set_xlabel(GAMMA_LABEL)
    ax.set_ylabel(r"$t(\gamma) = 2\,[\ln\hat r(\gamma_\mathrm{MLE}) - \ln\hat r(\gamma)]$")
    ax.grid(alpha=0.25)
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=7, frameon=False)
    footer(fig, run_name, source)
    return _finish(fig, "Test-statistic profiles of individual HST lenses")


def _interval_marks(g, t, interval, mle):
    """``(lo, hi, mle, note)`` of fig. 6's annotation: the interval's ends (None without
    one), the MLE (the grid minimum of ``t`` unless given) and the interval's flags."""
    note = ""
    if isinstance(interval, Interval):
        lo, hi = interval.lower, interval.upper
        mle = interval.mle if mle is None else mle
        if interval.multimodal:
            note += f"; hull of {len(interval.regions)} regions"
        if interval.lower_at_edge or interval.upper_at_edge:
            note += "; open at the prior edge"
    elif interval is not None:
        lo, hi = map(float, interval)
    else:
        lo = hi = None
    if mle is None:
        mle = float(g[np.argmin(t)])
    return lo, hi, mle, note


def _draw_hatched_bands(ax, bands) -> None:
    """The reference code's a = 1 bands ``(band_nfw, band_tnfw)``, hatched."""
    for label, band, color in zip(("NFW", "tNFW"), bands, (C_NFW, C_TNFW)):
        if band is not None:
            ax.axvspan(
                *band,
                fill=False,
                hatch="///",
                ec=color,
                lw=0.8,
                label=f"{label}, reference code's sets, $a$ = 1 (68%)",
            )


def hst_combined(
    gammas,
    t_combined,
    tau_13: float,
    band_nfw: tuple[float, float] | None,
    band_tnfw: tuple[float, float] | None,
    mle: float | None = None,
    interval: Interval | tuple[float, float] | None = None,
    *,
    run_name: str,
    source: str | None = None,
    kind: str = "t",
    n_images: int = 13,
    ymax: float | None = None,
    reference_bands: tuple | None = None,
) -> Figure:
    """Fig. 6: the combined HST profile with its calibrated 68% interval and the CDM bands.

    ``t_combined``: t(γ) (or ``ln r̂`` with ``kind='log_ratio'``) of the stack of all HST
    images; ``tau_13``: the calibrated threshold for that N; ``interval``: an
    :class:`~subslope.stats.intervals.Interval` (edge/multimodal flags are stated in the
    annotation) or ``(lo, hi)``; ``band_nfw``/``band_tnfw``: ``(lo, hi)`` 68% ranges
    (16–84%) of the a = 1 NFW/tNFW stack MLEs (Fig. 4 at a = 1), shaded;
    ``reference_bands``: ``(band_nfw, band_tnfw)`` of the reference code's sets (Fig. 4's
    second panel at a = 1), hatched.
    """
    g = np.asarray(gammas, dtype=np.float64)
    t = _to_t(t_combined, g, kind)
    if t.shape != g.shape:
        raise ValueError(f"t_combined must have the grid's shape {g.shape}, got {t.shape}")
    lo, hi, mle, note = _interval_marks(g, t, interval, mle)
    fig = Figure(figsize=(5.8, 4.3))
    ax = fig.subplots()
    bands = []
    if band_nfw is not None:
        bands.append(("CDM NFW subhalos, $a$ = 1 (68%)", band_nfw, C_NFW))
    if band_tnfw is not None:
        bands.append(("CDM tNFW subhalos, $a$ = 1 (68%)", band_tnfw, C_TNFW))
    _draw_bands(ax, bands)
    _draw_hatched_bands(ax, reference_bands or ())
    ax.plot(g, t, color=C_HST, lw=2, label=f"HST, {n_images} lenses combined")
    ax.axhline(
        tau_13,
        color="k",
        ls="--",
        lw=1,
        label=rf"calibrated 68% threshold $\tau_{{{n_images}}}$ = {tau_13:.3g}",
    )
    if lo is not None:
        for v in (lo, hi):
            ax.axvline(v, color=C_HST, ls=":", lw=1.2)
        txt = rf"$\gamma_\mathrm{{MLE}} = {mle:.2f}^{{+{hi - mle:.2f}}}_{{-{mle - lo:.2f}}}$" + note
        ax.text(
            0.03, 0.97, txt, transform=ax.transAxes, ha="left", va="top", fontsize=9, color=C_HST
        )
    top = ymax if ymax is not None else max(4 * tau_13, min(float(t.max()), 12 * tau_13))
    ax.set_ylim(0, top * 1.03)
    ax.set_xlim(g[0], g[-1])
    ax.set_xlabel(GAMMA_LABEL)
    ax.set_ylabel(r"$t(\gamma)$ of the combined profile")
    ax.grid(alpha=0.25)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2, fontsize=7, frameon=False)
    footer(fig, run_name, source)
    return _finish(fig, "Subhalo slope of the combined HST lenses vs CDM")


# ---------------------------------------------------------------------------------------
# coverage
# ---------------------------------------------------------------------------------------
def coverage_figure(
    table,
    levels,
    coverages_empirical,
    coverages_wilks=None,
    *,
    run_name: str,
    source: str | None = None,
) -> Figure:
    """Calibration check: held-out coverage per stack size, and expected-coverage curves.

    Left: observed coverage at the table's level (0.68) for each N with its binomial
    error bar, with the empirical thresholds τ_N (filled) and with Wilks' χ²₁ threshold
    (hollow), the calibrated ones with the σ of
    :func:`subslope.stats.calibration.coverage_sigma` where the table has it (the threshold's
    own scatter included); the target is the horizontal line. Right: coverage against credibility
    level (``levels``); ``coverages_empirical``/``coverages_wilks`` are one curve ``(L,)``
    or a mapping ``N → (L,)``. A calibrated procedure follows the diagonal within the grey
    ±2σ binomial band of the fewest held-out stacks of any N; below it means
    over-confident intervals.
    """
    needed = {
        "n_images",
        "coverage",
        "coverage_err",
        "coverage_wilks",
        "coverage_wilks_err",
        "n_heldout",
    }
    missing = needed - set(table.columns)
    if missing:
        raise ValueError(f"coverage_figure: table lacks column(s) {sorted(missing)}")
    level = float(table["level"].iloc[0]) if "level" in table.columns else 0.68
    lv = np.asarray(levels, dtype=np.float64)
    fig = Figure(figsize=(9.0, 4.2))
    ax1, ax2 = fig.subplots(1, 2)
    _coverage_panel(ax1, table, level)
    _curves_panel(ax2, lv, coverages_empirical, coverages_wilks, level)
    n_held = int(np.nanmin(table["n_heldout"])) if len(table) else 0
    if n_held > 0:  # where a calibrated curve of n_held independent stacks may wander
        half = 2 * np.sqrt(lv * (1 - lv) / n_held)
        ax2.fill_between(
            lv, lv - half, lv + half, color="0.6", alpha=0.25, lw=0, zorder=0,
            label=f"±2σ binomial, {n_held} held-out stacks",
        )  # fmt: skip
        ax2.legend(fontsize=6.5, frameon=False, loc="upper left")
    footer(fig, run_name, source)
    return _finish(fig, "Calibration of the test-statistic threshold on held-out stacks")


def _coverage_panel(ax1, table, level: float) -> None:
    """Held-out coverage per N at ``level``, calibrated and Wilks thresholds."""
    n = table["n_images"].to_numpy()
    ax1.axhline(level, color="0.4", ls="--", lw=1, label=f"target {level:.0%}")
    ax1.errorbar(
        n - 0.08,
        table["coverage"],
        yerr=table["coverage_sigma"] if "coverage_sigma" in table else table["coverage_err"],
        fmt="o",
        color=C_HST,
        capsize=2.5,
        label=r"calibrated $\tau_N$",
    )
    ax1.errorbar(
        n + 0.08,
        table["coverage_wilks"],
        yerr=table["coverage_wilks_err"],
        fmt="o",
        mfc="white",
        color="0.35",
        capsize=2.5,
        label=r"Wilks $\chi^2_1$",
    )
    for ni, nh in zip(n, table["n_heldout"], strict=True):
        ax1.annotate(
            f"{nh}",
            (ni, 0.02),
            xycoords=("data", "axes fraction"),
            ha="center",
            fontsize=6,
            color="0.4",
        )
    ax1.set_xticks(n)
    ax1.set_xlabel("images per stack $N$ (numbers: held-out stacks)")
    ax1.set_ylabel(f"held-out coverage of the {level:.0%} interval")
    span = max(
        0.12,
        float(np.nanmax(np.abs(np.r_[table["coverage"], table["coverage_wilks"]] - level))) + 0.05,
    )
    ax1.set_ylim(max(0, level - span), min(1, level + span))
    ax1.grid(alpha=0.25)
    ax1.legend(fontsize=7, frameon=False, loc="upper right")


def _curves_panel(ax2, lv, coverages_empirical, coverages_wilks, level: float) -> None:
    """Expected coverage against credibility level, one curve per N."""
    ax2.plot([0, 1], [0, 1], color="0.4", ls="--", lw=1, label="ideal")
    emp = (
        coverages_empirical
        if isinstance(coverages_empirical, Mapping)
        else {None: coverages_empirical}
    )
    wil = (
        (coverages_wilks if isinstance(coverages_wilks, Mapping) else {None: coverages_wilks})
        if coverages_wilks is not None
        else {}
    )
    cmap = colormaps["viridis"]
    keys = list(emp)
    for i, key in enumerate(keys):
        color = C_HST if key is None else cmap(i / max(len(keys) - 1, 1) * 0.85)
        suffix = "" if key is None else f", N={key}"
        ax2.plot(lv, np.asarray(emp[key]), color=color, lw=1.6, label="calibrated" + suffix)
        if key in wil:
            ax2.plot(lv, np.asarray(wil[key]), color=color, lw=1.0, ls=":", label="Wilks" + suffix)
    ax2.axvline(level, color="0.7", lw=0.8)
    ax2.set_xlim(0, 1)
    ax2.set_ylim(0, 1)
    ax2.set_aspect("equal")
    ax2.set_xlabel("credibility level")
    ax2.set_ylabel("held-out coverage")
    ax2.grid(alpha=0.25)
    ax2.legend(fontsize=6.5, frameon=False, loc="upper left")
