"""Lens-light fit (subslope.physics.light.fit): exact recovery of a noise-free Sérsic,
recovery on simulated lenses at the training S/N, and the HST-derived prior preset."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from subslope.physics.grid import pixel_grid
from subslope.physics.instrument import gaussian_psf
from subslope.physics.light.fit import fit_lens_light, prior_from_fits, sersic_model

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
            [15.2, np.log(6.0), 6.0, -0.2, 0.1, -0.1, 0.05, 0.0],
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
    assert np.all(fit.chi2_dof < 1e-3)


def test_recovery_on_simulated_lenses_with_arcs_and_noise():
    """Lens light from the hst_fits prior, a lensed Sérsic source of 20.5-22.5 mag and the
    detector noise: the arcs are masked, the light recovered (benchmarks/lens_light_fit.py
    measures 200 lenses the same way)."""
    from subslope.physics.instrument import Instrument, add_noise
    from subslope.physics.light.sersic import e1e2_to_q_phi
    from subslope.render.pipeline import RenderSettings, render
    from subslope.simulation.macro import sample_macro
    from subslope.simulation.scenes import Scene

    scene = Scene.from_config(
        "train",
        {
            "lens_light": {"prior": "hst_fits"},
            "source": {"kind": "sersic", "mag": {"dist": "uniform", "low": 20.5, "high": 22.5}},
            "components": {"subhalos": False, "los": False},
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
    assert fit.mask.mean() > 0.3 and np.all(np.isfinite(fit.model))


def test_hst_fits_preset_is_the_prior_derived_from_the_hst_fits(data_dir):
    from subslope import config as cfgmod
    from subslope.io.observations import find_lens_centre, load_hst
    from subslope.simulation.observing import build_instrument, build_psf
    from subslope.simulation.scenes import LENS_LIGHT_PRIORS

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
    )
    derived = prior_from_fits(fit.mag, fit.r_sersic, fit.n_sersic, fit.q)
    assert derived == LENS_LIGHT_PRIORS["hst_fits"]
    # the paper's prior covers none of the 13 fitted magnitudes
    assert np.all(fit.mag < LENS_LIGHT_PRIORS["table1"]["mag"]["low"])


def test_prior_from_fits_rounds_outwards_and_clips():
    p = prior_from_fits([15.004, 16.0], [1.0, 30.0], [0.6, 9.0], [0.5, 1.0])
    assert p["mag"] == {"dist": "uniform", "low": 14.5, "high": 16.5}
    assert p["r_sersic"]["low"] == 0.8 and p["r_sersic"]["high"] == 20.0
    assert p["n_sersic"]["low"] == 0.5 and p["n_sersic"]["high"] == 8.0
    assert p["e1"] == {"dist": "uniform", "low": -0.39, "high": 0.39}


def test_bad_images_are_refused():
    with pytest.raises(ValueError, match="B, H, W"):
        _fit(np.zeros((100, 100)), [[0, 0]], [1.0])
    bad = np.zeros((1, 100, 100))
    bad[0, 3, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        _fit(bad, [[0, 0]], [1.0])
