"""Empirical thresholds, stacks, splits and coverage (subslope.stats.calibration)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy import stats

from subslope.stats.calibration import (
    FewSamplesWarning,
    calibration_table,
    coverage,
    coverage_sigma,
    expected_coverage,
    make_stacks,
    overconfident,
    split,
    stack_t_true,
    threshold,
    thresholds,
    wilks_coverage,
    wilks_threshold,
)
from subslope.stats.intervals import gamma_grid

G = gamma_grid()


def test_wilks_threshold():
    assert wilks_threshold() == pytest.approx(0.98895, abs=1e-4)
    assert wilks_threshold(0.95) == pytest.approx(3.8415, abs=1e-4)
    with pytest.raises(ValueError, match="level"):
        wilks_threshold(1.0)


def test_threshold_recovers_chi2_quantile(rng):
    t = rng.chisquare(1, size=20_000)
    tau = threshold(t, 0.68)
    q = stats.chi2.ppf(0.68, 1)
    # Sampling error of a quantile: √(α(1−α)/n) / f(q).
    se = np.sqrt(0.68 * 0.32 / t.size) / stats.chi2.pdf(q, 1)
    assert abs(tau - q) < 3 * se
    # It is the conformal order statistic, within one rank of numpy's 'higher' quantile.
    srt = np.sort(t)
    k = int(np.ceil(0.68 * (t.size + 1)))
    assert tau == srt[k - 1]
    assert np.searchsorted(srt, np.quantile(t, 0.68, method="higher")) - (k - 1) in (-1, 0, 1)


def test_threshold_order_statistic_small_sample_and_warning():
    t = np.arange(1.0, 11.0)  # 10 values; k = ⌈0.68·11⌉ = 8
    with pytest.warns(FewSamplesWarning, match="only 10 samples"):
        assert threshold(t, 0.68) == 8.0
    with pytest.warns(FewSamplesWarning), pytest.raises(ValueError, match="too few"):
        threshold(t, 0.95)  # ⌈0.95·11⌉ = 11 > 10
    assert np.isinf(thresholds(t, [0.95])[0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        threshold(np.arange(60.0))  # no warning at >= 50 samples
    with pytest.raises(ValueError, match=">= 0"):
        threshold(-t)
    with pytest.raises(ValueError, match="non-finite"):
        threshold([1.0, np.nan] * 30)


def test_independent_stacks_are_the_first_images_of_distinct_sets():
    gamma = np.repeat([1.5, 2.0, 2.5], 4)
    set_index = np.repeat([7, 3, 9], 4)
    order = np.array([3, 0, 2, 1, 7, 4, 6, 5, 11, 8, 10, 9])  # rows not in set order
    st = make_stacks(gamma[order], set_index[order], 2, mode="independent")
    assert len(st) == 3 and sorted(st.set_id.tolist()) == [3, 7, 9]
    for rows, sid in zip(st.indices, st.set_id, strict=True):
        members = np.flatnonzero(set_index[order] == sid)
        assert rows.tolist() == members[:2].tolist()  # the set's first two rows
    assert len(np.unique(st.indices)) == st.indices.size  # no image in two stacks
    with pytest.raises(ValueError, match="mode must be one of"):
        make_stacks(gamma, set_index, 2, mode="random")
    with pytest.raises(ValueError, match="n_stacks applies to mode='disjoint' only"):
        make_stacks(gamma, set_index, 2, n_stacks=5, mode="independent")


def test_make_stacks_distinct_images_within_one_set(rng):
    n_sets, size = 40, 13
    gamma = np.repeat(rng.uniform(1.1, 2.9, n_sets), size)
    set_index = np.repeat(np.arange(100, 100 + n_sets), size)
    perm = rng.permutation(gamma.size)  # images of a set need not be contiguous
    gamma, set_index = gamma[perm], set_index[perm]
    for n in (1, 4, 13):
        st = make_stacks(gamma, set_index, n, rng=1)
        assert st.indices.shape == (n_sets * (size // n), n)
        assert len(np.unique(st.indices)) == st.indices.size  # disjoint: no image used twice
        for row, g, s in zip(st.indices, st.gamma, st.set_id, strict=True):
            assert len(set(row)) == n
            assert np.all(set_index[row] == s) and np.all(gamma[row] == g)
    more = make_stacks(
        gamma, set_index, 5, rng=2, n_stacks=300
    )  # > 80 disjoint ones: overlapping extras
    assert more.indices.shape == (300, 5)
    assert all(len(set(r)) == 5 and len(set(set_index[r])) == 1 for r in more.indices)
    fewer = make_stacks(gamma, set_index, 5, rng=2, n_stacks=10)
    assert len(fewer) == 10 and len(np.unique(fewer.indices)) == 50
    # Deterministic for a seed.
    np.testing.assert_array_equal(
        make_stacks(gamma, set_index, 4, rng=7).indices,
        make_stacks(gamma, set_index, 4, rng=7).indices,
    )
    with pytest.raises(ValueError, match="no set has"):
        make_stacks(gamma, set_index, 14)
    bad = gamma.copy()
    bad[0] += 0.1
    with pytest.raises(ValueError, match="mixes true"):
        make_stacks(bad, set_index, 3)


def test_split_is_deterministic_and_by_key():
    keys = np.repeat(np.arange(50), 3)
    m = split(keys, seed=3)
    np.testing.assert_array_equal(m, split(keys, seed=3))
    assert m.sum() == 75
    for k in range(50):  # all stacks of a key on one side
        assert len(set(m[keys == k])) == 1
    assert not np.array_equal(m, split(keys, seed=4))


def test_coverage_fraction_error_and_wilson():
    t = np.r_[np.zeros(68), np.full(32, 5.0)]
    p, se, (lo, hi) = coverage(t, 1.0)
    assert p == 0.68 and se == pytest.approx(np.sqrt(0.68 * 0.32 / 100))
    assert lo < 0.68 < hi and 0 <= lo and hi <= 1
    p, se, (lo, hi) = coverage(np.zeros(100), 1.0)
    assert p == 1.0 and se == 0.0 and hi == 1.0 and lo < 1.0  # Wilson stays informative at p = 1


# ---------------------------------------------------------------------------------------
# Gaussian toy where Wilks' theorem is exact: x_i ~ N(θ, σ²), ln r(θ) = −(x − θ)²/(2σ²).
SIGMA = 0.15


def _gaussian_toy(rng, n_sets=1000, size=13, scale=1.0):
    theta = np.repeat(rng.uniform(1.6, 2.4, n_sets), size)
    x = theta + SIGMA * rng.normal(size=theta.size)
    profiles = -scale * (x[:, None] - G[None, :]) ** 2 / (2 * SIGMA**2)
    return theta, np.repeat(np.arange(n_sets), size), profiles


def test_gaussian_toy_coverage_is_nominal_for_every_n(rng):
    theta, set_index, profiles = _gaussian_toy(rng)
    t_by_n, keys_by_n = {}, {}
    for n in (1, 2, 5, 13):
        st = make_stacks(theta, set_index, n, rng=n)
        t_by_n[n] = stack_t_true(profiles, G, st)
        keys_by_n[n] = st.set_id
    table = calibration_table(t_by_n, keys_by_n, seed=0)
    assert list(table.n_images) == [1, 2, 5, 13]
    assert set(table.columns) >= {
        "tau",
        "tau_wilks",
        "n_calibration",
        "n_heldout",
        "coverage",
        "coverage_err",
    }
    for row in table.itertuples():
        assert row.n_calibration + row.n_heldout == len(t_by_n[row.n_images])
        sig = np.sqrt(0.68 * 0.32 / row.n_heldout)
        assert abs(row.coverage - 0.68) < 3 * sig, row
        assert abs(row.coverage_wilks - 0.68) < 3 * sig, row  # Wilks is exact here
        se_tau = np.sqrt(0.68 * 0.32 / len(t_by_n[row.n_images])) / stats.chi2.pdf(0.989, 1)
        assert abs(row.tau - 0.989) < 4 * se_tau + 0.03, row  # + grid interpolation bias
    # Expected-coverage curves follow the diagonal (N = 1: 6500 held-out stacks).
    is_cal = split(keys_by_n[1], seed=0)
    lv, cov = expected_coverage(t_by_n[1][is_cal], t_by_n[1][~is_cal])
    assert lv.shape == cov.shape == (99,)
    assert np.max(np.abs(cov - lv)) < 0.03
    _, cov_w = wilks_coverage(t_by_n[1][~is_cal], lv)
    assert np.max(np.abs(cov_w - lv)) < 0.03
    assert np.all(np.diff(cov) >= 0)


def test_overconfident_estimator_breaks_wilks_not_empirical_calibration(rng):
    # ln r̂ = 2 × the true log-likelihood ratio: t doubles, Wilks under-covers (P(χ²₁ ≤ 0.494) ≈
    # 0.52).
    theta, set_index, profiles = _gaussian_toy(rng, n_sets=400, scale=2.0)
    st = make_stacks(theta, set_index, 1, rng=0)
    t = stack_t_true(profiles, G, st)
    table = calibration_table({1: t}, {1: st.set_id})
    row = table.iloc[0]
    sig = np.sqrt(0.68 * 0.32 / row.n_heldout)
    assert abs(row.coverage - 0.68) < 3 * sig
    assert row.coverage_wilks < 0.68 - 5 * sig
    assert row.tau == pytest.approx(2 * 0.989, rel=0.1)


def test_coverage_sigma_is_the_scatter_of_split_conformal_coverage():
    """Exact t ~ χ²₁ (any continuous law gives the same ranks): the held-out coverage of
    the conformal threshold of 200 calibration stacks, measured on 200 others, scatters
    by coverage_sigma over many repetitions; the binomial error of the held-out stacks
    alone is √2 too small for an even split."""
    rng = np.random.default_rng(11)
    n_c = n_h = 200
    cov = np.array(
        [np.mean(rng.random(n_h) <= threshold(rng.random(n_c), 0.68)) for _ in range(4000)]
    )
    sigma = float(coverage_sigma(0.68, n_c, n_h))
    assert abs(cov.std() / sigma - 1) < 0.06
    assert cov.std() > 1.3 * np.sqrt(0.68 * 0.32 / n_h)
    assert abs(cov.mean() - 0.68) < 0.003 + 1 / (n_c + 1)  # conformal: at or just above
    assert overconfident(0.58, sigma, 0.68) and not overconfident(0.60, sigma, 0.68)
