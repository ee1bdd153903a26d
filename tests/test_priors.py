"""Tests of subslope.simulation.priors: each family against its distribution, errors, seeding."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from subslope.simulation.priors import (
    DISTRIBUTIONS,
    Fixed,
    JointNormal,
    Normal,
    PowerLaw,
    Prior,
    PriorError,
    Uniform,
    UniformInt,
)

N = 20_000


def test_uniform_matches_distribution(rng):
    p = Prior.from_config({"dist": "uniform", "low": 0.9, "high": 1.3}, "k")
    assert isinstance(p, Uniform)
    x = p.sample(rng, N)
    assert x.dtype == np.float64 and x.shape == (N,)
    assert stats.kstest(x, stats.uniform(0.9, 0.4).cdf).pvalue > 1e-3
    assert p.support == (0.9, 1.3) and p.mean == pytest.approx(1.1)


def test_truncated_normal_matches_distribution_and_bounds(rng):
    p = Prior.from_config({"dist": "normal", "mean": 2.0, "std": 0.2, "low": 1.9, "high": 2.9}, "k")
    x = p.sample(rng, N)
    assert x.min() >= 1.9 and x.max() <= 2.9
    ref = stats.truncnorm((1.9 - 2.0) / 0.2, (2.9 - 2.0) / 0.2, loc=2.0, scale=0.2)
    assert stats.kstest(x, ref.cdf).pvalue > 1e-3
    assert p.mean == pytest.approx(ref.mean())
    assert abs(x.mean() - ref.mean()) < 5 * ref.std() / math.sqrt(N)


def test_one_sided_and_untruncated_normal(rng):
    p = Prior.from_config({"dist": "normal", "mean": 0.8, "std": 0.15, "low": 0.01}, "k")
    x = p.sample(rng, N)
    assert x.min() >= 0.01 and p.support == (0.01, math.inf)
    q = Prior.from_config({"dist": "normal", "mean": 1.0, "std": 2.0}, "k")
    assert stats.kstest(q.sample(rng, N), stats.norm(1.0, 2.0).cdf).pvalue > 1e-3


def test_far_tail_truncation_is_exact_and_does_not_hang(rng):
    # Probability mass ~1e-15 under the untruncated normal: rejection would never finish.
    p = Prior.from_config({"dist": "normal", "mean": 0.0, "std": 1.0, "low": 8.0, "high": 9.0}, "k")
    x = p.sample(rng, 5000)
    assert np.all((x >= 8.0) & (x <= 9.0))
    assert stats.kstest(x, stats.truncnorm(8.0, 9.0).cdf).pvalue > 1e-3


def test_uniform_int_inclusive_chi2(rng):
    p = Prior.from_config({"dist": "uniform_int", "low": 0, "high": 9}, "k")
    x = p.sample(rng, N)
    assert x.dtype == np.float64 and np.all(x == np.round(x))
    counts = np.bincount(x.astype(int), minlength=10)
    assert counts.size == 10 and counts[0] > 0 and counts[9] > 0  # both ends reached
    assert stats.chisquare(counts).pvalue > 1e-3
    assert p.mean == 4.5
    big = Prior.from_config({"dist": "uniform_int", "low": 0, "high": 3000}, "k").sample(rng, N)
    assert big.min() >= 0 and big.max() <= 3000


def test_power_law_matches_distribution(rng):
    p = Prior.from_config({"dist": "power_law", "slope": -1.9, "low": 1e7, "high": 1e10}, "k")
    x = p.sample(rng, N)
    assert x.min() >= 1e7 and x.max() <= 1e10
    # Analytic CDF of p(x) ∝ x^-1.9 written independently of the implementation.
    k = -0.9
    cdf = lambda m: (m**k - 1e7**k) / (1e10**k - 1e7**k)  # noqa: E731
    assert stats.kstest(x, cdf).pvalue > 1e-3
    assert abs(x.mean() - p.mean) < 5 * x.std() / math.sqrt(N)
    flat = Prior.from_config({"dist": "power_law", "slope": -1.0, "low": 1.0, "high": 100.0}, "k")
    assert stats.kstest(np.log10(flat.sample(rng, N)), stats.uniform(0, 2).cdf).pvalue > 1e-3


def test_fixed_and_number_shorthand(rng):
    assert np.all(Prior.from_config({"dist": "fixed", "value": 0.3}, "k").sample(rng, 5) == 0.3)
    p = Prior.from_config(1.5, "k")
    assert isinstance(p, Fixed) and p.mean == 1.5 and p.support == (1.5, 1.5)


@pytest.mark.parametrize("cls", [Uniform, Normal, UniformInt, PowerLaw, Fixed])
def test_round_trip_to_config(cls):
    examples = {
        Uniform: {"dist": "uniform", "low": -1.0, "high": 2.0},
        Normal: {"dist": "normal", "mean": 2.0, "std": 0.1, "low": 1.1, "high": 2.9},
        UniformInt: {"dist": "uniform_int", "low": 0, "high": 3},
        PowerLaw: {"dist": "power_law", "slope": -1.9, "low": 1e7, "high": 1e10},
        Fixed: {"dist": "fixed", "value": 0.0},
    }
    d = examples[cls]
    assert Prior.from_config(d, "k").to_config() == d
    assert set(DISTRIBUTIONS) == {"uniform", "normal", "uniform_int", "power_law", "fixed"}


def test_same_seed_same_draws():
    p = Prior.from_config({"dist": "normal", "mean": 2.0, "std": 0.1, "low": 1.1, "high": 2.9}, "k")
    a = p.sample(np.random.default_rng(5), 100)
    b = p.sample(np.random.default_rng(5), 100)
    c = p.sample(np.random.default_rng(6), 100)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


@pytest.mark.parametrize(
    "spec, needle",
    [
        ({"dist": "uniform", "low": 1.3, "high": 0.9}, "scenes.train.main_lens.theta_e.low"),
        ({"dist": "gauss", "mean": 1}, "scenes.train.main_lens.theta_e.dist"),
        ({"dist": "uniform", "low": 0.9}, "missing high"),
        ({"dist": "uniform", "low": 0.9, "high": 1.3, "mean": 1}, "unknown key(s) mean"),
        ({"dist": "normal", "mean": 1.0, "std": 0.0}, "scenes.train.main_lens.theta_e.std"),
        (
            {"dist": "normal", "mean": 0.0, "std": 0.01, "low": 5.0, "high": 6.0},
            "no probability mass",
        ),
        ({"dist": "uniform", "low": "a", "high": 1.0}, "scenes.train.main_lens.theta_e.low"),
        ({"dist": "uniform", "low": float("nan"), "high": 1.0}, "finite"),
        ({"dist": "uniform_int", "low": 0.5, "high": 3}, "integer"),
        ({"dist": "power_law", "slope": -1.9, "low": 0.0, "high": 1e10}, "must be > 0"),
        ("uniform", "is not a prior"),
    ],
)
def test_bad_specs_raise_naming_the_key(spec, needle):
    with pytest.raises(PriorError) as err:
        Prior.from_config(spec, key="scenes.train.main_lens.theta_e")
    assert needle in str(err.value)
    assert isinstance(err.value, ValueError)
    assert "scenes.train.main_lens.theta_e" in str(err.value)


def test_sample_requires_generator():
    with pytest.raises(TypeError):
        Uniform(0.0, 1.0).sample(np.random.RandomState(0), 3)


def test_truncated_normal_quantile_matches_scipy():
    from scipy import stats

    from subslope.simulation.priors import truncated_normal_quantile

    rng = np.random.default_rng(5)
    u = np.concatenate([rng.random(4000), [0.0, 1.0, 1e-15, 1 - 1e-15]])
    cases = [(-0.5, 0.3), (-6.5, 0.31), (-0.31, 6.5), (2.0, 9.0), (-9.0, -2.0), (-40, 40)]
    for a, b in cases:
        x = truncated_normal_quantile(u, a, b)
        ref = stats.truncnorm.ppf(u, a, b)
        assert np.all((x >= a) & (x <= b)), (a, b)
        np.testing.assert_allclose(x, ref, rtol=1e-7, atol=1e-9, err_msg=f"[{a}, {b}]")
    # far tails, where the normal CDF underflows: scipy's own evaluation
    x = truncated_normal_quantile(u, 40.0, 41.0)
    np.testing.assert_allclose(x, stats.truncnorm.ppf(u, 40.0, 41.0), rtol=1e-12)
    # broadcasting, per-element bounds
    a = np.array([-1.0, 0.5, -3.0])
    np.testing.assert_allclose(
        truncated_normal_quantile(0.25, a, a + 1), stats.truncnorm.ppf(0.25, a, a + 1), rtol=1e-10
    )


JOINT = {
    "mean": {"a": 1.0, "b": -2.0},
    "cov": [[0.04, 0.03], [0.03, 0.09]],
    "widen": 1.5,
    "low": {"a": -10.0, "b": -20.0},
    "high": {"a": 10.0, "b": 20.0},
}


def test_joint_normal_far_box_is_the_widened_normal(rng):
    p = JointNormal.from_config(JOINT, "k")
    x = p.sample(rng, N)
    np.testing.assert_allclose([x["a"].mean(), x["b"].mean()], [1.0, -2.0], atol=0.01)
    cov = np.cov([x["a"], x["b"]])
    np.testing.assert_allclose(cov, 2.25 * np.array(JOINT["cov"]), rtol=0.05)
    assert stats.kstest(x["b"], stats.norm(-2.0, 1.5 * 0.3).cdf).pvalue > 1e-3
    assert JointNormal.from_config(p.to_config(), "k") == p


def test_joint_normal_stays_in_a_tight_box_and_keeps_the_correlation(rng):
    spec = dict(JOINT, low={"a": 0.9, "b": -2.5}, high={"a": 1.2, "b": -1.0})
    x = JointNormal.from_config(spec, "k").sample(rng, N)
    assert x["a"].min() >= 0.9 and x["a"].max() <= 1.2
    assert x["b"].min() >= -2.5 and x["b"].max() <= -1.0
    assert np.corrcoef(x["a"], x["b"])[0, 1] > 0.05
    again = JointNormal.from_config(spec, "k").sample(np.random.default_rng(5), 10)
    same = JointNormal.from_config(spec, "k").sample(np.random.default_rng(5), 10)
    assert all(np.array_equal(again[k], same[k]) for k in again)


@pytest.mark.parametrize(
    "change, needle",
    [
        ({"cov": [[0.04, 0.05], [0.05, 0.04]]}, "positive definite"),
        ({"cov": [[0.04, 0.03], [0.02, 0.09]]}, "symmetric"),
        ({"cov": [[0.04]]}, "2 x 2"),
        ({"widen": 0.0}, "widen"),
        ({"low": {"a": 0.0}}, "k.low"),
        ({"mean": {"a": 50.0, "b": 0.0}}, "k.mean.a"),
        ({"extra": 1}, "exactly the keys"),
    ],
)
def test_joint_normal_bad_specs_name_the_key(change, needle):
    with pytest.raises(PriorError, match=needle):
        JointNormal.from_config({**JOINT, **change}, "k")
