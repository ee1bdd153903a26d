"""Profiles, stacking, MLE refinement, test statistic and intervals (subslope.stats.intervals)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from subslope.nre.evaluate import log_ratio_profiles
from subslope.stats.intervals import (
    gamma_grid,
    interval,
    intervals,
    mle,
    refine_max,
    stack,
    t_at,
    test_statistic,
)

G = gamma_grid()


def parabola(mu, s, g=G, amp=3.0):
    """ln r = amp − (γ − μ)² / (2 s²): t(γ) = ((γ − μ)/s)², crossings at μ ± s√τ."""
    return amp - (g - mu) ** 2 / (2 * s**2)


# ---------------------------------------------------------------------------------------
def test_gamma_grid():
    assert G.shape == (181,) and G[0] == 1.1 and G[-1] == 2.9
    np.testing.assert_allclose(np.diff(G), 0.01, rtol=1e-9)
    for bad in [dict(low=2.0, high=1.0), dict(n=2), dict(n=10.5), dict(high=np.inf)]:
        with pytest.raises(ValueError):
            gamma_grid(**bad)


def test_stack_is_sum_of_profiles(rng):
    p = rng.normal(size=(20, G.size))
    np.testing.assert_allclose(stack(p[:5]), p[0] + p[1] + p[2] + p[3] + p[4], rtol=1e-12)
    idx = np.array([[0, 3, 7], [1, 2, 19]])
    np.testing.assert_allclose(
        stack(p, idx), np.stack([p[0] + p[3] + p[7], p[1] + p[2] + p[19]]), rtol=1e-12
    )
    np.testing.assert_allclose(stack(p.reshape(4, 5, -1)), p.reshape(4, 5, -1).sum(1))
    labels = np.repeat(["b", "a"], 10)
    out = stack(p, labels)  # np.unique order: "a" then "b"
    np.testing.assert_allclose(out[0], p[10:].sum(0), rtol=1e-12)
    np.testing.assert_allclose(out[1], p[:10].sum(0), rtol=1e-12)
    with pytest.raises(ValueError, match="indices"):
        stack(p, np.array([[0, 20]]))
    with pytest.raises(ValueError, match="one label per image"):
        stack(p, np.arange(3))


@pytest.mark.parametrize("mu", [1.4567891, 2.000049, 2.51234, 1.1049, 2.8951])
def test_mle_recovers_parabola_vertex_off_grid(mu):
    p = parabola(mu, 0.2)
    assert abs(mle(p, G) - mu) < 1e-10
    g_hat, v_hat = refine_max(p, G)
    assert abs(v_hat - 3.0) < 1e-10  # refined maximum value, above the grid maximum
    assert v_hat >= p.max()


def test_mle_non_uniform_grid_and_vectorised():
    g = np.sort(np.concatenate([np.linspace(1.1, 2.9, 50), [1.733, 1.7401, 2.2222]]))
    mus = np.array([[1.7377, 2.2], [1.5, 2.61]])
    p = parabola(mus[..., None], 0.3, g)
    out = mle(p, g)
    assert out.shape == (2, 2)
    np.testing.assert_allclose(out, mus, atol=1e-10)


def test_mle_edges_and_flat_top():
    assert mle(G, G) == 2.9  # increasing: the last node
    assert mle(-G, G) == 1.1
    assert mle(parabola(3.5, 0.3), G) == 2.9  # vertex outside the prior range → clipped to the edge
    assert mle(np.zeros(G.size), G) == 1.1  # flat: not concave, the first grid argmax is kept
    p = np.zeros(G.size)
    p[50:52] = 1.0  # two tied nodes: the parabola through (0, 1, 1) peaks midway
    assert mle(p, G) == pytest.approx(0.5 * (G[50] + G[51]), abs=1e-12)
    # A skewed peak: the vertex is clipped to the neighbouring nodes at most.
    q = np.full(G.size, -10.0)
    q[90], q[91] = 0.0, -1e-12
    assert G[89] <= mle(q, G) <= G[91]


def test_test_statistic_nonnegative_and_zero_at_mle(rng):
    mu = 1.98765
    t = test_statistic(parabola(mu, 0.15), G)
    assert t.min() >= 0
    np.testing.assert_allclose(t, ((G - mu) / 0.15) ** 2, atol=1e-9)
    assert t_at(parabola(mu, 0.15), G, mu) == pytest.approx(0.0, abs=1e-12)
    noisy = rng.normal(size=(7, G.size))
    tn = test_statistic(noisy, G)
    assert tn.shape == (7, G.size) and np.all(tn >= 0)
    assert np.all(tn.min(axis=1) < 1.0)
    with pytest.raises(ValueError, match="non-finite"):
        test_statistic(np.full(G.size, np.nan), G)
    with pytest.raises(ValueError, match="shape"):
        test_statistic(np.zeros(10), G)


def test_interval_parabola_crossings():
    mu, s, tau = 2.13456, 0.1, 0.989
    iv = interval(parabola(mu, s), G, tau)
    # Linear interpolation of a parabola between nodes 0.01 apart: error ≤ h²/(8 s²)·s/(2√τ)/… ≪
    # 1e-3.
    assert iv.lower == pytest.approx(mu - s * np.sqrt(tau), abs=3e-4)
    assert iv.upper == pytest.approx(mu + s * np.sqrt(tau), abs=3e-4)
    assert iv.mle == pytest.approx(mu, abs=1e-10)
    assert not (iv.multimodal or iv.lower_at_edge or iv.upper_at_edge)
    assert iv.minus > 0 and iv.plus > 0 and len(iv.regions) == 1
    # The bounds are exact crossings of the piecewise-linear t that t_at evaluates.
    assert t_at(parabola(mu, s), G, iv.lower) == pytest.approx(tau, abs=1e-9)
    assert t_at(parabola(mu, s), G, iv.upper) == pytest.approx(tau, abs=1e-9)


def test_interval_tent_profile_exact():
    # ln r = −|γ − 2|/w is linear between nodes: linear interpolation is exact.
    w, tau = 0.05, 1.3
    iv = interval(-np.abs(G - 2.0) / w, G, tau)
    assert iv.mle == pytest.approx(2.0, abs=1e-12)
    assert iv.lower == pytest.approx(2.0 - tau * w / 2, abs=1e-12)
    assert iv.upper == pytest.approx(2.0 + tau * w / 2, abs=1e-12)


def test_interval_bimodal_gives_regions_hull_and_flag():
    # Two peaks: the main one at 1.6 and a secondary one at 2.5 only 0.2 lower in ln r.
    p = np.maximum(parabola(1.6, 0.05, amp=0.0), parabola(2.5, 0.05, amp=-0.2))
    iv = interval(p, G, 0.989)
    assert iv.multimodal and len(iv.regions) == 2
    (a, b), (c, d) = iv.regions
    assert a < 1.6 < b < c < 2.5 < d
    assert (iv.lower, iv.upper) == (a, d)
    assert iv.mle == pytest.approx(1.6, abs=1e-10)
    assert iv.contains(2.5) and not iv.contains(2.0)
    # With a tighter threshold the secondary peak (t = 0.4) drops out.
    assert not interval(p, G, 0.3).multimodal


def test_interval_monotonic_profile_flags_edges():
    iv = interval(5.0 * G, G, 0.989)  # rising: MLE at 2.9, open upper side
    assert iv.upper_at_edge and not iv.lower_at_edge
    assert iv.mle == iv.upper == 2.9
    assert iv.lower == pytest.approx(2.9 - 0.989 / 10, abs=1e-12)
    iv = interval(-5.0 * G, G, 0.989)
    assert iv.lower_at_edge and iv.lower == 1.1 and not iv.upper_at_edge
    iv = interval(np.zeros(G.size), G, 0.989)  # uninformative: the whole prior range
    assert iv.lower_at_edge and iv.upper_at_edge and (iv.lower, iv.upper) == (1.1, 2.9)
    with pytest.raises(ValueError, match="threshold"):
        interval(G, G, -1.0)


def test_t_at_agrees_with_interval_membership(rng):
    profiles = np.cumsum(rng.normal(size=(30, G.size)), axis=1) * 0.3
    tau = 0.989
    probes = rng.uniform(1.1, 2.9, size=30)
    tv = t_at(profiles, G, probes)
    for row, gp, tval, iv in zip(profiles, probes, tv, intervals(profiles, G, tau), strict=True):
        assert (tval <= tau) == iv.contains(gp)
        assert t_at(row, G, iv.mle) == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError, match="grid range"):
        t_at(profiles[0], G, 3.0)


# ---------------------------------------------------------------------------------------
class _MeanModel(torch.nn.Module):
    """Stand-in estimator: ln r(x|γ) = −(γ − 2 − mean(x))² · 10, mean over the kept pixels."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.ones(()))
        self.calls = []

    def log_ratio_grid(self, x, gammas):
        self.calls.append(tuple(x.shape))
        assert not torch.is_grad_enabled()
        m = x.flatten(1).mean(1) * self.w
        return -10.0 * (gammas[None, :] - 2.0 - m[:, None]) ** 2


def test_log_ratio_profiles_preprocesses_and_batches(rng):
    from subslope.nre.preprocess import preprocess

    images = rng.normal(3.0, 2.0, size=(7, 20, 20)).astype(np.float32)
    te, cx, cy = rng.uniform(0.2, 0.35, 7), rng.uniform(-0.05, 0.05, 7), np.zeros(7)
    model = _MeanModel()
    out = log_ratio_profiles(model, images, te, cx, cy, {"mean": 3.0, "std": 2.0}, G, batch_size=3)
    assert out.shape == (7, G.size) and out.dtype == np.float64
    assert model.calls == [(3, 20, 20), (3, 20, 20), (1, 20, 20)]
    x = preprocess(images, te, cx, cy, 3.0, 2.0)
    m = x.reshape(7, -1).mean(1)
    np.testing.assert_allclose(mle(out, G), 2.0 + m, atol=1e-5)


def test_log_ratio_profiles_real_estimator_matches_log_ratio_grid(rng):
    from subslope.nre import build_model
    from subslope.nre.preprocess import preprocess

    torch.manual_seed(0)
    model = build_model({"preset": "reduced"}, gamma_mean=2.0, gamma_std=0.5).eval()
    images = rng.normal(1.0, 1.0, size=(3, 100, 100)).astype(np.float32)
    grid = gamma_grid(n=11)
    out = log_ratio_profiles(
        model, images, 1.1, 0.0, 0.0, (1.0, 1.0), grid, batch_size=2, device="cpu"
    )
    with torch.no_grad():
        ref = (
            model.log_ratio_grid(
                torch.as_tensor(preprocess(images, 1.1, 0.0, 0.0, 1.0, 1.0)),
                torch.as_tensor(grid, dtype=torch.float32),
            )
            .double()
            .numpy()
        )
    np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-5)


def test_symmetrized_profiles_average_the_eight_views(rng):
    """symmetrize=True is the mean of the profiles of the eight rotated/mirrored images
    (lens at the origin, so the mask turns into itself), and gives a rotated image the
    same profile as the original."""
    from subslope.nre import build_model
    from subslope.nre.augment import dihedral

    torch.manual_seed(1)
    model = build_model({"preset": "reduced"}, gamma_mean=2.0, gamma_std=0.5).eval()
    images = rng.normal(1.0, 1.0, size=(3, 100, 100)).astype(np.float32)
    grid = gamma_grid(n=11)

    def prof(x, sym):
        return log_ratio_profiles(
            model, x, 1.1, 0.0, 0.0, (1.0, 1.0), grid, device="cpu", symmetrize=sym
        )

    sym = prof(images, True)
    views = [prof(dihedral(torch.as_tensor(images), k).numpy(), False) for k in range(8)]
    np.testing.assert_allclose(sym, np.mean(views, axis=0), rtol=1e-5, atol=1e-5)
    assert np.max(np.abs(views[1] - views[0])) > 1e-3  # the network itself is not invariant
    turned = prof(dihedral(torch.as_tensor(images), 3).numpy(), True)
    np.testing.assert_allclose(turned, sym, rtol=1e-5, atol=1e-5)
