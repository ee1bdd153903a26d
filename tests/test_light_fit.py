"""Lens-light fit (subslope.physics.light.fit): exact recovery of a noise-free Sérsic on a
sky pedestal, recovery on simulated lenses at the training S/N, and the HST-derived prior
presets (the joint prior of the pedestal fits, the older boxes of fits without it)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from subslope.physics.grid import pixel_grid
from subslope.physics.instrument import gaussian_psf
from subslope.physics.light.fit import (
    fit_lens_light,
    joint_prior_from_fits,
    prior_from_fits,
    sersic_model,
    sky_prior_from_fits,
)

pytestmark = pytest.mark.usefixtures("one_thread")

PSF = gaussian_psf(0.1, 0.04).numpy()


def _fit(images, centres, theta_e, **kw):
    return fit_lens_light(
        images,
        PSF,
        centres,
        theta_e,
        background_sigma=0.004,
        exposure_time=2200.0,
        pixel_scale=0.04,
        **kw,
    )


def test_noise_free_sersic_is_recovered_exactly():
    truth = torch.tensor(
        [
            [16.0, np.log(1.5), 4.0, 0.1, -0.05, 0.03, -0.02, 0.0],
            [15.2, np.log(6.0), 6.0, -0.2, 0.1, -0.1, 0.05, 0.12],
        ],
        dtype=torch.float64,
    )
    xs, ys = pixel_grid(100, 0.04, dtype=torch.float64)
    images = sersic_model(truth, (xs[None], ys[None]), torch.as_tensor(PSF), 0.04).numpy()
    start = truth[:, 5:7].numpy() + 0.02
    fit = _fit(images, start, [1.0, 1.0], clip=None, iterations=40)
    np.testing.assert_allclose(fit.mag, truth[:, 0], atol=2e-3)
    np.testing.assert_allclose(fit.r_sersic, np.exp(truth[:, 1]), rtol=5e-3)
    np.testing.assert_allclose(fit.n_sersic, truth[:, 2], atol=5e-3)
    np.testing.assert_allclose(fit.x, truth[:, 5], atol=1e-4)
    np.testing.assert_allclose(fit.background, truth[:, 7], atol=1e-4)
    assert np.all(fit.chi2_dof < 1e-3)


def test_float32_model_agrees_with_the_float64_reference():
    truth = torch.tensor(
        [[16.0, np.log(1.5), 4.0, 0.1, -0.05, 0.03, -0.02, 0.05]], dtype=torch.float64
    )
    xs, ys = pixel_grid(100, 0.04, dtype=torch.float64)
    images = sersic_model(truth, (xs[None], ys[None]), torch.as_tensor(PSF), 0.04).numpy()
    images = images + np.random.default_rng(0).normal(0, 0.004, images.shape)
    kw = {"clip": None, "iterations": 20}
    ref = _fit(images, truth[:, 5:7].numpy() + 0.02, [1.0], **kw)
    f32 = _fit(images, truth[:, 5:7].numpy() + 0.02, [1.0], dtype=torch.float32, **kw)
    np.testing.assert_allclose(f32.mag, ref.mag, atol=2e-3)
    np.testing.assert_allclose(f32.r_sersic, ref.r_sersic, rtol=5e-3)
    np.testing.assert_allclose(f32.n_sersic, ref.n_sersic, atol=1e-2)
    np.testing.assert_allclose(f32.background, ref.background, atol=2e-4)
    assert f32.model.dtype == np.float64 and np.all(np.isfinite(f32.model))
    with pytest.raises(ValueError, match="dtype"):
        _fit(images, [[0, 0]], [1.0], dtype=torch.float16)


def test_recovery_on_simulated_lenses_with_arcs_and_noise():
    """Lens light from the hst_joint prior on a sky level, a lensed Sérsic source of
    20.5-22.5 mag and the detector noise: the arcs are masked, the light and the sky
    recovered (benchmarks/lens_light_fit.py measures 200 lenses the same way)."""
    from subslope.physics.instrument import Instrument, add_noise
    from subslope.physics.light.sersic import e1e2_to_q_phi
    from subslope.render.pipeline import RenderSettings, render
    from subslope.simulation.macro import sample_macro
    from subslope.simulation.scenes import Scene

    scene = Scene.from_config(
        "train",
        {
            "lens_light": {"prior": "hst_joint"},
            "source": {"kind": "sersic", "mag": {"dist": "uniform", "low": 20.5, "high": 22.5}},
            "components": {"subhalos": False, "los": False, "sky": True},
            "sky": {"level": {"dist": "uniform", "low": 0.0, "high": 0.2}},
        },
    )
    macro = sample_macro(scene, 12, np.random.default_rng(3))
    s = RenderSettings(device="cpu", dtype=torch.float64, compile="off")
    inst = Instrument()
    images = add_noise(render(macro, torch.as_tensor(PSF), s), 7, instrument=inst).numpy()
    fit = fit_lens_light(
        images,
        PSF,
        np.stack([macro["lens_x"], macro["lens_y"]], 1),
        macro["theta_e"],
        background_sigma=inst.background_sigma,
        exposure_time=inst.total_exposure_time,
        pixel_scale=0.04,
    )
    q, _ = e1e2_to_q_phi(torch.as_tensor(macro["light_e1"]), torch.as_tensor(macro["light_e2"]))
    assert np.median(np.abs(fit.mag - macro["light_mag"])) < 0.15
    assert np.median(np.abs(fit.r_sersic / macro["light_r"] - 1)) < 0.3
    assert np.median(np.abs(fit.n_sersic - macro["light_n"])) < 0.8
    assert np.median(np.abs(fit.q - q.numpy())) < 0.03
    assert np.median(np.abs(fit.background - macro["sky_level"])) < 0.01
    assert fit.mask.mean() > 0.3 and np.all(np.isfinite(fit.model))


def _hst_fits(data_dir, **kw):
    from subslope import config as cfgmod
    from subslope.io.observations import find_lens_centre, load_hst
    from subslope.simulation.observing import build_instrument, build_psf

    cfg = cfgmod.validate({"data": {"resources_dir": str(data_dir)}})
    inst = build_instrument(cfg)
    obs = load_hst(data_dir / "hst")
    fit = fit_lens_light(
        np.stack([o.image for o in obs]),
        build_psf(cfg),
        np.array([find_lens_centre(o.image) for o in obs]),
        np.array([o.theta_e for o in obs]),
        background_sigma=inst.background_sigma,
        exposure_time=inst.total_exposure_time,
        pixel_scale=inst.pixel_scale,
        **kw,
    )
    return obs, fit


def test_hst_joint_preset_is_the_prior_of_the_pedestal_fits_and_they_are_plausible(data_dir):
    from subslope.physics.cosmology import arcsec_to_mpc
    from subslope.simulation.presets import LENS_LIGHT_PRIORS
    from subslope.stages.domain import JOINT_WIDEN

    obs, fit = _hst_fits(data_dir)
    derived = joint_prior_from_fits(fit.mag, fit.r_sersic, fit.n_sersic, fit.q, widen=JOINT_WIDEN)
    assert derived == LENS_LIGHT_PRIORS["hst_joint"]["joint"]
    # physical: SLACS-like early-type lenses, a few kpc and 15-18 mag, on a sky pedestal
    r_kpc = fit.r_sersic * 1e3 * arcsec_to_mpc(np.array([o.z_lens for o in obs]))
    assert np.all((fit.mag > 15.0) & (fit.mag < 18.0))
    assert np.all((r_kpc > 1.0) & (r_kpc < 15.0))
    assert np.all((fit.background > 0.0) & (fit.background < 0.25))
    sky = sky_prior_from_fits(fit.background, widen=JOINT_WIDEN)
    assert sky["low"] == 0.0 and 0.03 < sky["mean"] < 0.12


def test_without_the_pedestal_the_hst_sky_becomes_sersic_wings(data_dir):
    _, with_b = _hst_fits(data_dir)
    _, fit = _hst_fits(data_dir, pedestal=False)
    # R runs to the fit box's edge and the lenses come out brighter than with the pedestal
    assert np.sum(fit.r_sersic > 9.9) >= 3 and np.all(fit.r_sersic >= with_b.r_sersic)
    assert np.all(fit.mag < with_b.mag) and np.all(fit.mag < 16.5)
    # the older uniform boxes (preset hst_fits) came from such fits, with a 20" box
    box = prior_from_fits(fit.mag, fit.r_sersic, fit.n_sersic, fit.q)
    assert box["r_sersic"]["high"] == 10.0


def test_prior_from_fits_rounds_outwards_and_clips():
    p = prior_from_fits([15.004, 16.0], [1.0, 30.0], [0.6, 9.0], [0.5, 1.0])
    assert p["mag"] == {"dist": "uniform", "low": 14.5, "high": 16.5}
    assert p["r_sersic"]["low"] == 0.8 and p["r_sersic"]["high"] == 10.0
    assert p["n_sersic"]["low"] == 0.5 and p["n_sersic"]["high"] == 8.0
    assert p["e1"] == {"dist": "uniform", "low": -0.39, "high": 0.39}


def test_bad_images_are_refused():
    with pytest.raises(ValueError, match="B, H, W"):
        _fit(np.zeros((100, 100)), [[0, 0]], [1.0])
    bad = np.zeros((1, 100, 100))
    bad[0, 3, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        _fit(bad, [[0, 0]], [1.0])


def test_joint_prior_from_fits_is_the_sample_moments_widened():
    rng = np.random.default_rng(0)
    mag, r, n, q = (
        rng.normal(16, 0.5, 50),
        np.exp(rng.normal(0, 0.3, 50)),
        rng.normal(4, 1, 50),
        rng.uniform(0.5, 0.9, 50),
    )
    p = joint_prior_from_fits(mag, r, n, q, widen=2.0)
    assert list(p["mean"]) == ["mag", "ln_r", "n", "q"]
    np.testing.assert_allclose(p["mean"]["ln_r"], np.log(r).mean(), rtol=1e-4)
    np.testing.assert_allclose(np.array(p["cov"]), np.cov([mag, np.log(r), n, q]), rtol=1e-4)
    assert p["widen"] == 2.0
    with pytest.raises(ValueError, match="at least 5"):
        joint_prior_from_fits(mag[:3], r[:3], n[:3], q[:3])
