"""Cross-checks of light profiles and noise against lenstronomy (reference only)."""

import numpy as np
import pytest
import torch

from subslope.physics.grid import pixel_grid
from subslope.physics.instrument import Instrument, noise_sigma_map
from subslope.physics.light import sersic_ellipse, sersic_total_flux

pytestmark = pytest.mark.reference

PARAMS = [
    dict(amp=3.2, R_sersic=0.8, n_sersic=0.5, e1=0.0, e2=0.0, center_x=0.0, center_y=0.0),
    dict(amp=1.0, R_sersic=0.6, n_sersic=1.0, e1=0.15, e2=-0.08, center_x=0.03, center_y=-0.05),
    dict(amp=0.4, R_sersic=1.1, n_sersic=2.3, e1=-0.1, e2=0.1, center_x=-0.11, center_y=0.07),
    dict(amp=7.0, R_sersic=0.9, n_sersic=4.0, e1=0.05, e2=0.19, center_x=0.013, center_y=0.021),
    dict(amp=2.0, R_sersic=0.5, n_sersic=8.0, e1=-0.2, e2=-0.02, center_x=0.2, center_y=-0.1),
]


@pytest.mark.parametrize("kw", PARAMS, ids=[f"n{p['n_sersic']}" for p in PARAMS])
def test_sersic_ellipse_matches_lenstronomy(kw):
    from lenstronomy.LightModel.light_model import LightModel

    x, y = pixel_grid(100, 0.04, supersample=2, dtype=torch.float64)
    ref = LightModel(["SERSIC_ELLIPSE"]).surface_brightness(
        x.numpy().ravel(), y.numpy().ravel(), [kw]
    )
    ours = sersic_ellipse(
        x,
        y,
        kw["amp"],
        kw["R_sersic"],
        kw["n_sersic"],
        kw["e1"],
        kw["e2"],
        kw["center_x"],
        kw["center_y"],
    )
    np.testing.assert_allclose(ours.numpy().ravel(), ref, rtol=1e-6, atol=0)
    tot = LightModel(["SERSIC_ELLIPSE"]).total_flux([kw])[0]
    ours_tot = sersic_total_flux(
        torch.tensor(kw["amp"], dtype=torch.float64), kw["R_sersic"], kw["n_sersic"]
    )
    assert float(ours_tot) == pytest.approx(tot, rel=1e-10)


def test_noise_sigma_matches_lenstronomy_single_band():
    from lenstronomy.SimulationAPI.observation_api import SingleBand

    inst = Instrument()
    band = SingleBand(
        pixel_scale=inst.pixel_scale,
        exposure_time=inst.exposure_time,
        magnitude_zero_point=inst.magnitude_zero_point,
        read_noise=inst.read_noise,
        ccd_gain=inst.ccd_gain,
        sky_brightness=inst.sky_brightness,
        num_exposures=inst.num_exposures,
        seeing=None,
        psf_type="NONE",
    )  # data_count_unit='e-' (default, as paltas)
    img = np.random.default_rng(0).gamma(0.5, 2.0, size=(20, 20))
    img[0, :5] = [-0.5, 0.0, 1e-4, 1e-2, 50.0]
    ref = band.estimate_noise(img.copy())
    ours = noise_sigma_map(torch.as_tensor(img), inst).numpy()
    np.testing.assert_allclose(ours, ref, rtol=1e-12)
    assert inst.background_sigma == pytest.approx(band.background_noise, rel=1e-12)
