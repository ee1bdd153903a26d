"""Tests of subslope.simulation.subhalos: mass function, slopes, placement, lens-parameter
conversion."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import optimize, stats

from subslope.simulation import subhalos as sh
from subslope.simulation.macro import sample_macro
from subslope.simulation.scenes import Scene, scenes_from_config

NPIX, DELTA = 100, 0.04


def ring_image(radius=1.1, width=0.08, cx=0.0, cy=0.0, npix=NPIX, delta=DELTA):
    x = (np.arange(npix) - (npix - 1) / 2) * delta
    xx, yy = np.meshgrid(x, x)  # image[j, i] at (x_i, y_j)
    r = np.hypot(xx - cx, yy - cy)
    return np.exp(-0.5 * ((r - radius) / width) ** 2)


def to_pixel(x, y, h, w, delta=DELTA):
    """Pixel (j, i) containing the point (x, y) on the design.md grid."""
    return np.floor(y / delta + h / 2).astype(int), np.floor(x / delta + w / 2).astype(int)


def powerlaw_slope_mle(m, lo, hi):
    """MLE of k in p(m) ∝ m^k on [lo, hi] (root of the score)."""
    mean_log = np.mean(np.log(m))

    def score(k):
        a = k + 1.0
        # d/dk log normalisation: E_k[ln m]
        e = (hi**a * np.log(hi) - lo**a * np.log(lo)) / (hi**a - lo**a) - 1.0 / a
        return mean_log - e

    return optimize.brentq(score, -3.5, -1.05)


def test_offsets_and_system_index():
    counts = np.array([2, 0, 3])
    assert np.array_equal(sh.offsets(counts), [0, 2, 2, 5])
    assert np.array_equal(sh.system_index(counts), [0, 0, 2, 2, 2])
    with pytest.raises(ValueError, match="counts"):
        sh.offsets(np.array([1, -1]))


def test_mass_function_slope_recovered(rng):
    m = sh.sample_masses(300_000, rng)
    assert m.min() >= 1e7 and m.max() <= 1e10
    assert abs(powerlaw_slope_mle(m, 1e7, 1e10) - (-1.9)) < 0.02
    # A different slope is recovered too (the estimator is not fixed at -1.9).
    m2 = sh.sample_masses(300_000, rng, slope=-1.5)
    assert abs(powerlaw_slope_mle(m2, 1e7, 1e10) - (-1.5)) < 0.02


def test_subhalo_gammas_truncation_and_mean(rng):
    counts = np.array([40_000, 40_000, 40_000])
    gsys = np.array([1.1, 2.0, 2.9])
    g = sh.sample_subhalo_gammas(gsys, counts, rng, 0.1, (1.01, 2.99))
    assert g.min() >= 1.01 and g.max() <= 2.99
    for b, mu in enumerate(gsys):
        part = g[40_000 * b : 40_000 * (b + 1)]
        ref = stats.truncnorm(
            (1.01 - mu) / (0.1 * mu), (2.99 - mu) / (0.1 * mu), loc=mu, scale=0.1 * mu
        )
        assert abs(part.mean() - ref.mean()) < 5 * ref.std() / np.sqrt(part.size)
        assert stats.kstest(part, ref.cdf).pvalue > 1e-3
    # At γ = 2.9 the truncation pulls the mean well below 2.9; at 2.0 it barely matters.
    assert g[80_000:].mean() < 2.8
    assert abs(g[40_000:80_000].mean() - 2.0) < 0.005
    with pytest.raises(ValueError, match="shape"):
        sh.sample_subhalo_gammas(gsys[:2], counts, rng)


def test_arc_candidates_threshold():
    img = ring_image()
    idx = sh.arc_candidates(img, 0.2)
    flat = img.ravel()
    assert np.all(flat[idx] > 0.2 * flat.max())
    assert np.count_nonzero(flat > 0.2 * flat.max()) == idx.size
    assert sh.arc_candidates(np.zeros((5, 5)), 0.2).size == 0
    with pytest.raises(ValueError, match="threshold_fraction"):
        sh.arc_candidates(img, 1.2)


def test_place_on_arc_hits_only_bright_pixels(rng):
    imgs = np.stack([ring_image(1.1), ring_image(0.6, cx=0.3), ring_image(1.5, width=0.05)])
    imgs[2] = imgs[2] * 7.0 + 0.01  # per-image maximum, not a global one
    counts = np.array([20_000, 0, 20_000, 20_000])
    # An off-centre ring: catches x/y (column/row) mix-ups that a centred ring hides.
    imgs = np.concatenate([imgs, ring_image(0.5, cx=-0.8, cy=0.4)[None]])
    x, y = sh.place_on_arc(imgs, counts, rng, DELTA, 0.2)
    assert x.shape == y.shape == (60_000,)
    sys = sh.system_index(counts)
    j, i = to_pixel(x, y, NPIX, NPIX)
    for b in (0, 2, 3):
        mask = imgs[b] > 0.2 * imgs[b].max()
        sel = sys == b
        assert np.all(mask[j[sel], i[sel]]), f"system {b}: subhalo off the arc"
        # Every candidate pixel is reachable and used roughly equally often.
        hits = np.bincount(j[sel] * NPIX + i[sel], minlength=NPIX * NPIX)[mask.ravel()]
        assert np.count_nonzero(hits) > 0.95 * mask.sum()
        assert stats.chisquare(hits).pvalue > 1e-3
    # Offsets within the pixel are uniform.
    fx = (x / DELTA + NPIX / 2) % 1.0
    assert stats.kstest(fx, "uniform").pvalue > 1e-3
    with pytest.raises(ValueError, match="no pixel above"):
        sh.place_on_arc(np.zeros((1, 10, 10)), np.array([3]), rng, DELTA)


def test_threshold_changes_candidate_set(rng):
    img = ring_image()[None]
    x, y = sh.place_on_arc(img, np.array([20_000]), rng, DELTA, 0.5)
    j, i = to_pixel(x, y, NPIX, NPIX)
    assert np.all(img[0][j, i] > 0.5 * img.max())


def test_place_everywhere_uniform(rng):
    x, y = sh.place_everywhere(np.array([5000, 7000]), rng, NPIX, DELTA)
    assert x.size == 12_000
    for v in (x, y):
        assert stats.kstest(v, stats.uniform(-2.0, 4.0).cdf).pvalue > 1e-3
    assert stats.pearsonr(x, y)[1] > 1e-3


# docs/simulation.md: for M200 = 1e8 M_sun at z_l = 0.2, z_s = 0.6, a round EPL has
# α(1") = θ_E^(γ-1) (the amplitude).
REFERENCE_AMP = [(1.01, 1.03e-2), (1.5, 4.34e-4), (2.0, 4.26e-4), (2.9, 6.81e-4)]


def test_epl_amplitude_matches_reference_values():
    gammas = np.array([g for g, _ in REFERENCE_AMP])
    ref = np.array([a for _, a in REFERENCE_AMP])
    counts = np.array([4, 0, 4])
    mass = np.full(8, 1e8)
    amp = sh.epl_amplitudes(mass, np.tile(gammas, 2), counts, [0.2, 0.3, 0.2], [0.6, 0.7, 0.6])
    assert np.all(np.isfinite(amp))
    np.testing.assert_allclose(amp[:4], ref, rtol=0.01)
    np.testing.assert_allclose(amp[4:], ref, rtol=0.01)


def test_epl_amplitude_uses_each_systems_redshifts():
    from subslope.physics.cosmology import epl_amp_from_m200

    counts = np.array([2, 3])
    mass = np.array([1e7, 1e9, 1e8, 3e8, 1e10])
    gamma = np.array([1.2, 2.5, 1.8, 2.0, 2.9])
    zl, zs = np.array([0.16, 0.24]), np.array([0.55, 0.69])
    amp = sh.epl_amplitudes(mass, gamma, counts, zl, zs)
    direct = [
        epl_amp_from_m200(m, g, zl[b], zs[b])
        for m, g, b in zip(mass, gamma, sh.system_index(counts))
    ]
    np.testing.assert_allclose(amp, direct, rtol=1e-12)


def test_nfw_parameters_follow_concentration_relation(rng):
    from subslope.physics.concentration import dutton_maccio_c200, truncation_radius_arcsec
    from subslope.physics.cosmology import nfw_params_from_m200_c

    counts = np.array([3, 0, 2])
    mass = np.array([1e7, 1e8, 1e9, 1e8, 1e10])
    zl, zs = np.array([0.2, 0.22, 0.18]), np.array([0.6, 0.6, 0.65])
    r_sub = np.array([0.5, 1.0, 1.5, 0.0, 2.0])
    sys = sh.system_index(counts)
    out = sh.nfw_parameters(
        mass, counts, zl, zs, rng, multiplier=[2.0, 1.0, 0.5], scatter_dex=0.0, r_sub=r_sub
    )
    mult = np.array([2.0, 0.5])[[0, 0, 0, 1, 1]]
    np.testing.assert_allclose(out["c200"], mult * dutton_maccio_c200(mass, zl[sys]), rtol=1e-12)
    for n in range(5):
        r_s, a_rs = nfw_params_from_m200_c(mass[n], out["c200"][n], zl[sys[n]], zs[sys[n]])
        assert out["r_s"][n] == pytest.approx(r_s, rel=1e-12)
        assert out["alpha_rs"][n] == pytest.approx(a_rs, rel=1e-12)
        r = max(r_sub[n], sh.R_SUB_FLOOR)
        assert out["r_t"][n] == pytest.approx(
            truncation_radius_arcsec(mass[n], r, zl[sys[n]]), rel=1e-12
        )
    # 0.1 dex scatter around the median.
    big = np.full(20_000, 1e8)
    c = sh.nfw_parameters(big, np.array([20_000]), 0.2, 0.6, rng, 1.0, 0.1)["c200"]
    resid = np.log10(c / dutton_maccio_c200(1e8, 0.2))
    assert abs(resid.mean()) < 0.005 and abs(resid.std() - 0.1) < 0.005


def test_sample_subhalos_epl_scene(rng):
    scene = scenes_from_config({})["test_epl"]
    macro = sample_macro(scene, 26, rng)
    imgs = np.stack(
        [
            ring_image(t, cx=x, cy=y)
            for t, x, y in zip(macro["theta_e"], macro["lens_x"], macro["lens_y"])
        ]
    )
    pop = sh.sample_subhalos(scene, macro, np.random.default_rng(3), imgs)
    again = sh.sample_subhalos(scene, macro, np.random.default_rng(3), imgs)
    n = int(macro["n_sub"].sum())
    assert pop.mass.shape == pop.gamma.shape == pop.amp.shape == pop.x.shape == (n,)
    assert pop.c200 is None and pop.r_t is None
    assert all(np.array_equal(v, again.arrays()[k]) for k, v in pop.arrays().items())
    assert np.all((pop.gamma >= 1.01) & (pop.gamma <= 2.99))
    assert np.all(np.isfinite(pop.amp)) and np.all(pop.amp > 0)
    assert np.all(np.abs(pop.e1) <= 0.2) and np.all(np.abs(pop.e2) <= 0.2)
    bright = imgs > 0.2 * imgs.max(axis=(1, 2), keepdims=True)
    # on a bright pixel up to the float16 rounding of the stored positions (<= 2^-10 arcsec)
    on_arc = np.zeros(n, dtype=bool)
    for dx, dy in ((0, 0), (1, 1), (1, -1), (-1, 1), (-1, -1)):
        j, i = to_pixel(pop.x + dx * 2.0**-10, pop.y + dy * 2.0**-10, NPIX, NPIX)
        on_arc |= bright[pop.system, j, i]
    assert np.all(on_arc)
    with pytest.raises(ValueError, match="smooth_images"):
        sh.sample_subhalos(scene, macro, rng, None)


def test_sample_subhalos_tnfw_scene(rng):
    scene = scenes_from_config({})["tnfw"]
    macro = sample_macro(scene, 13, rng, multiplier=2.0)
    pop = sh.sample_subhalos(scene, macro, rng)
    n = int(macro["n_sub"].sum())
    assert pop.gamma is None and pop.amp is None
    for k in ("c200", "r_s", "alpha_rs", "r_t", "x", "y"):
        v = getattr(pop, k)
        assert v.shape == (n,) and np.all(np.isfinite(v)), k
    assert np.all(np.abs(pop.x) <= 2.0) and np.all(np.abs(pop.y) <= 2.0)
    nfw = sh.sample_subhalos(scenes_from_config({})["nfw"], macro, rng)
    assert nfw.r_t is None and nfw.r_s is not None


def test_sample_subhalos_without_subhalos(rng):
    scene = Scene.from_config("train", {"components": {"subhalos": False}})
    macro = sample_macro(scene, 5, rng)
    pop = sh.sample_subhalos(scene, macro, rng)
    assert np.array_equal(pop.counts, np.zeros(5)) and pop.mass.size == 0


def test_per_system_generators_give_each_system_alone(rng):
    """One Generator per system: the batch equals each system sampled alone from its own."""
    scene = scenes_from_config({})["test_epl"]
    macro = {k: v[:4] for k, v in sample_macro(scene, 13, rng).items()}
    imgs = np.stack(
        [
            ring_image(t, cx=x, cy=y)
            for t, x, y in zip(macro["theta_e"], macro["lens_x"], macro["lens_y"])
        ]
    )
    seeds = np.random.SeedSequence(11).spawn(4)
    batch = sh.sample_subhalos(scene, macro, [np.random.default_rng(s) for s in seeds], imgs)
    alone = [
        sh.sample_subhalos(
            scene,
            {k: v[b : b + 1] for k, v in macro.items()},
            np.random.default_rng(seeds[b]),
            imgs[b : b + 1],
        )
        for b in range(4)
    ]
    for k, v in batch.arrays().items():
        assert np.array_equal(v, np.concatenate([a.arrays()[k] for a in alone])), k
    with pytest.raises(ValueError, match=r"sequence of 4 of them \(one per system\), got 3 items"):
        sh.sample_subhalos(scene, macro, [np.random.default_rng(s) for s in seeds[:3]], imgs)
