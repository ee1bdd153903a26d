"""The result figures build from synthetic inputs and are written as PDF + PNG (Agg)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from subslope.figures import paper as figures  # noqa: E402
from subslope.figures.save import save_figure  # noqa: E402
from subslope.stats.calibration import calibration_table, expected_coverage, split, wilks_coverage  # noqa: E402
from subslope.stats.intervals import gamma_grid, interval, test_statistic  # noqa: E402

G = gamma_grid()
RUN = "tiny-test"


def _footer_texts(fig: Figure) -> list[str]:
    return [t.get_text() for t in fig.texts]


def _check_saved(fig, tmp_path, stem):
    paths = save_figure(fig, tmp_path / "out" / stem, run_name=RUN)
    assert [p.suffix for p in paths] == [".pdf", ".png"]
    for p in paths:
        assert p.is_file() and p.stat().st_size > 1000
    assert paths[0].read_bytes()[:4] == b"%PDF"
    assert paths[1].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not [
        q for q in (tmp_path / "out").iterdir() if q.name.endswith(".tmp")
    ]  # no temporary left
    assert any(f"run_name={RUN!r}" in t for t in _footer_texts(fig))
    return paths


@pytest.fixture
def scatter_data(rng):
    gt = rng.uniform(1.1, 2.9, 120)
    m = np.clip(gt + rng.normal(0, 0.15, gt.size), 1.1, 2.9)
    lo, hi = np.clip(m - 0.2, 1.1, None), np.clip(m + 0.25, None, 2.9)
    return gt, m, lo, hi


def test_validation_and_stack_scatter(scatter_data, tmp_path):
    gt, m, lo, hi = scatter_data
    fig = figures.validation_scatter(
        gt, m, lo, hi, run_name=RUN, open_lower=lo <= 1.1, open_upper=hi >= 2.9, threshold=1.02
    )
    (ax,) = fig.axes
    inside = ((gt > 1.2) & (gt < 2.8)).sum()
    from matplotlib.collections import PathCollection, PolyCollection

    dots = [c for c in ax.collections if isinstance(c, PathCollection)]
    bands = [c for c in ax.collections if isinstance(c, PolyCollection)]
    assert sum(len(c.get_offsets()) for c in dots) == inside  # only 1.2 < γ < 2.8, faint
    assert len(dots) == 2 and len(bands) == 3  # closed/open points; γ_MLE, lower, upper bands
    median = next(line for line in ax.get_lines() if line.get_linewidth() == 2)
    x, y = median.get_data()
    ok = np.isfinite(y)
    assert ok.sum() >= 8 and np.all(np.abs(y[ok] - x[ok]) < 0.15)  # unbiased toy estimates
    assert ax.get_legend() is not None and "1:1" in [
        t.get_text() for t in ax.get_legend().get_texts()
    ]
    _check_saved(fig, tmp_path, "fig2_validation")
    fig3 = figures.stack_scatter(gt[:30], m[:30], lo[:30], hi[:30], run_name=RUN, threshold=1.1)
    assert "13" in fig3.get_suptitle()
    _check_saved(fig3, tmp_path, "fig3_stacks")
    with pytest.raises(ValueError, match="mle"):
        figures.validation_scatter(gt, m[:5], lo, hi, run_name=RUN)


def test_binned_quantiles():
    from subslope.figures.recovery import binned_quantiles

    x = np.linspace(0.0, 1.0, 1001)
    centres, q, counts = binned_quantiles(x, 2 * x, [0.0, 0.5, 1.0])
    assert np.allclose(centres, [0.25, 0.75]) and counts.tolist() == [500, 501]
    assert np.allclose(q[:, 1], [0.499, 1.5], atol=2e-3)  # median of 2x over each half
    assert np.allclose(q[:, 0], 2 * np.array([0.08, 0.58]), atol=3e-3)
    _, q, counts = binned_quantiles([0.1, 0.2], [1.0, 2.0], [0.0, 0.5, 1.0])
    assert counts.tolist() == [2, 0] and np.isnan(q).all()  # fewer than 3 points: no band
    with pytest.raises(ValueError, match="increasing"):
        binned_quantiles(x, x, [1.0, 0.0])


def test_concentration_grid(rng, tmp_path):
    a = np.array([0.25, 0.5, 1.0, 2.0, 4.0, 8.0])
    nfw = 1.6 + 0.2 * np.log2(a)[:, None] + rng.normal(0, 0.05, (a.size, 100))
    tnfw = nfw + 0.1
    fig = figures.concentration_grid(a, nfw, tnfw, run_name=RUN, hst=(2.51, 2.47, 2.56))
    (ax,) = fig.axes
    assert ax.get_xscale() == "log"
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert (
        any("NFW" in s for s in labels)
        and any("tNFW" in s for s in labels)
        and any("HST" in s for s in labels)
    )
    assert any("CDM" in t.get_text() for t in ax.texts)  # the a = 1 mark
    assert any(np.allclose(line.get_xdata(), 1.0) for line in ax.lines)
    _check_saved(fig, tmp_path, "fig4_concentration")
    with pytest.raises(ValueError, match="shape"):
        figures.concentration_grid(a, nfw[:3], run_name=RUN)


def _lnr(mu, s):
    return -((G - mu) ** 2) / (2 * s**2)


def test_hst_profiles_and_combined(tmp_path):
    names = ["SDSSJ0946+1006", "SDSSJ0029-0055", "SDSSJ0737+3216", "SDSSJ1627-0053"]
    lnr = {n: _lnr(2.2 + 0.1 * k, 0.3 + 0.05 * k) for k, n in enumerate(names)}
    fig5 = figures.hst_profiles(
        G, lnr, 1.05, run_name=RUN, kind="log_ratio", wilks=0.989, highlight=["SDSSJ0946+1006"]
    )
    (ax,) = fig5.axes
    assert len(ax.lines) == len(names) + 2  # curves + τ₁ + Wilks
    assert max(line.get_linewidth() for line in ax.lines) == 2.4  # SDSSJ0946+1006 highlighted
    np.testing.assert_allclose(ax.lines[0].get_ydata(), test_statistic(lnr[names[0]], G))
    _check_saved(fig5, tmp_path, "fig5_hst_profiles")

    comb = sum(lnr.values()) * 3
    iv = interval(comb, G, 1.1)
    t = test_statistic(comb, G)
    fig6 = figures.hst_combined(G, t, 1.1, (1.75, 1.95), (1.9, 2.1), interval=iv, run_name=RUN)
    (ax,) = fig6.axes
    assert len(ax.patches) == 2  # the NFW and tNFW bands
    labels = [x.get_text() for x in ax.get_legend().get_texts()]
    assert sum("a$ = 1" in s for s in labels) == 2
    assert any("MLE" in x.get_text() for x in ax.texts)
    vlines = [
        line.get_xdata()[0]
        for line in ax.lines
        if np.ptp(line.get_xdata()) == 0 and len(line.get_xdata()) == 2
    ]
    np.testing.assert_allclose(sorted(vlines), [iv.lower, iv.upper])
    _check_saved(fig6, tmp_path, "fig6_hst_combined")
    # A multimodal / edge interval is said so in the annotation.
    bi = np.maximum(_lnr(1.5, 0.05), _lnr(2.5, 0.05) - 0.2)
    fig = figures.hst_combined(
        G, bi, 0.989, None, None, interval=interval(bi, G, 0.989), run_name=RUN, kind="log_ratio"
    )
    assert any("hull of 2 regions" in x.get_text() for x in fig.axes[0].texts)


def test_coverage_figure(rng, tmp_path):
    t_by_n = {n: rng.chisquare(1, 400) * (1 + 0.1 * (n > 5)) for n in (1, 3, 13)}
    table = calibration_table(t_by_n)
    cal = split(np.arange(400), seed=0)
    lv, emp = expected_coverage(t_by_n[1][cal], t_by_n[1][~cal])
    _, wil = wilks_coverage(t_by_n[1][~cal], lv)
    fig = figures.coverage_figure(table, lv, emp, wil, run_name=RUN)
    ax1, ax2 = fig.axes
    assert len(ax1.containers) == 2  # two error-bar series (calibrated, Wilks)
    assert len(ax2.lines) == 4  # diagonal, calibrated, Wilks, level marker
    _check_saved(fig, tmp_path, "coverage")
    per_n = {n: expected_coverage(t[cal], t[~cal])[1] for n, t in t_by_n.items()}
    fig = figures.coverage_figure(table, lv, per_n, run_name=RUN)
    assert len(fig.axes[1].lines) == 2 + len(per_n)
    with pytest.raises(ValueError, match="lacks"):
        figures.coverage_figure(table.drop(columns="coverage"), lv, emp, run_name=RUN)
