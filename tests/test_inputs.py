"""Estimator input transforms (subslope.nre.inputs) and the lens-light fit they subtract
(subslope.physics.light.subtract): the per-pixel formulas, the stored fit and its model
images, shards with and without the fit, the whitening measured after the transform,
and the config keys that choose them."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from subslope.io.shards import LIGHT_FIT_GROUP, write_shard
from subslope.nre.data import ShardBatches
from subslope.nre.inputs import InputTransform, ShardLightModels
from subslope.nre.preprocess import preprocess, read_inputs
from subslope.nre.whitening import compute_whitening
from subslope.physics.grid import pixel_grid
from subslope.physics.instrument import gaussian_psf
from subslope.physics.light.fit import sersic_model
from subslope.physics.light.subtract import STORED, fit_input_light, model_images

pytestmark = pytest.mark.usefixtures("one_thread")

PSF = gaussian_psf(0.1, 0.04).numpy()
NPIX, SCALE, SIGMA_BG, T_EXP = 60, 0.04, 0.004, 2200.0
SNR = InputTransform("snr", SIGMA_BG, T_EXP)
SUBTRACTED = InputTransform("light_subtracted")


def _lenses(n: int) -> np.ndarray:
    """``n`` noise-free Sérsic lenses on a sky pedestal, float32 (e⁻/s per pixel)."""
    rng = np.random.default_rng(3)
    truth = np.column_stack(
        [
            rng.uniform(17.0, 18.0, n),
            np.log(rng.uniform(0.5, 1.5, n)),
            rng.uniform(2.0, 5.0, n),
            rng.uniform(-0.15, 0.15, (n, 2)),
            rng.uniform(-0.03, 0.03, (n, 2)),
            rng.uniform(0.0, 0.02, n),
        ]
    )
    xs, ys = pixel_grid(NPIX, SCALE, dtype=torch.float64)
    model = sersic_model(torch.as_tensor(truth), (xs[None], ys[None]), torch.as_tensor(PSF), SCALE)
    return model.numpy().astype(np.float32)


def _fit(images):
    n = len(images)
    return fit_input_light(
        images,
        np.zeros((n, 2)),
        np.full(n, 0.8),
        PSF,
        background_sigma=SIGMA_BG,
        exposure_time=T_EXP,
        pixel_scale=SCALE,
    )


def _shard(path, images, light_fit=None):
    n = len(images)
    return write_shard(
        path,
        images=images,
        params={
            "theta_e": np.full(n, 0.8),
            "lens_x": np.zeros(n),
            "lens_y": np.zeros(n),
            "set_index": np.arange(n),
            "noise_seed": np.arange(n, dtype=np.uint64),
            "gamma_sub": np.linspace(1.2, 2.8, n),
        },
        psf=PSF,
        subhalos={"counts": np.zeros(n, dtype=np.int64)},
        los={"counts": np.zeros(n, dtype=np.int64)},
        light_fit=light_fit,
        attrs={"seed": 1, "config": {"instrument": {"pixel_scale": SCALE}}},
    )


@pytest.fixture(scope="module")
def lenses():
    images = _lenses(5)
    return images, _fit(images)


def test_transforms_by_hand():
    d = np.array([[[-0.01, 0.0, 0.004, 4.0]]], dtype=np.float32)
    np.testing.assert_array_equal(InputTransform().apply(d), d)
    expected = d / np.sqrt(SIGMA_BG**2 + np.maximum(d, 0) / T_EXP)
    np.testing.assert_allclose(SNR.apply(d), expected, rtol=1e-6)
    assert SNR.apply(d)[0, 0, 1] == 0.0 and SNR.apply(d).dtype == np.float32
    np.testing.assert_allclose(SUBTRACTED.apply(d, d - 1.0), np.ones_like(d))
    with pytest.raises(ValueError, match="fitted lens-light model"):
        SUBTRACTED.apply(d)
    with pytest.raises(ValueError, match="does not match"):
        SUBTRACTED.apply(d, d[..., :2])


def test_bad_transforms_are_refused_with_the_allowed_values():
    with pytest.raises(ValueError, match=r"training.inputs = 'asinh'.*whitened"):
        InputTransform("asinh")
    with pytest.raises(ValueError, match="background_sigma > 0"):
        InputTransform("snr", 0.0, T_EXP)


def test_transform_round_trips_through_json():
    assert InputTransform.from_json(json.loads(json.dumps(SNR.to_json()))) == SNR
    assert InputTransform.from_json(None) == InputTransform()
    assert read_inputs({"mean": 0.0, "std": 1.0}) == InputTransform()
    assert read_inputs({"mean": 0.0, "std": 1.0, "inputs": SNR.to_json()}) == SNR


def test_stored_fit_rebuilds_the_lens_light(lenses):
    images, fit = lenses
    assert set(fit) == set(STORED) and all(v.shape == (5,) for v in fit.values())
    model = model_images(fit, PSF, NPIX, SCALE)
    assert model.dtype == np.float32 and np.isfinite(model).all()
    # noise-free lenses: the residual is a small fraction of every pixel's noise
    noise = np.sqrt(SIGMA_BG**2 + np.maximum(images, 0) / T_EXP)
    assert np.abs((images - model) / noise).max() < 0.1
    with pytest.raises(ValueError, match="missing"):
        model_images({k: v for k, v in fit.items() if k != "n_sersic"}, PSF, NPIX, SCALE)
    with pytest.raises(ValueError, match="r_sersic > 0"):
        model_images({**fit, "r_sersic": -fit["r_sersic"]}, PSF, NPIX, SCALE)


def test_shard_batches_subtract_the_stored_fit(tmp_path, lenses):
    images, fit = lenses
    path = _shard(tmp_path / "s.h5", images, fit)
    ds = ShardBatches([path], 5, (0.0, 1.0), shuffle=False, inputs=SUBTRACTED)
    model = model_images(fit, PSF, NPIX, SCALE)
    ref = preprocess(images - model, np.full(5, 0.8), 0.0, 0.0, 0.0, 1.0, pixel_scale=SCALE)
    # the float32 model of a batch of 2 and of 5 differ by a few units of its last place
    # (the vectorised and scalar loops round differently on some CPUs)
    tol = 8 * np.finfo(np.float32).eps * float(np.abs(model).max())
    np.testing.assert_allclose(ds[0]["x"][:, 0].numpy(), ref, atol=tol)
    # shuffled blocks cut by the batch boundaries: each image gets its own model
    ds = ShardBatches([path], 2, (0.0, 1.0), shuffle=True, block_size=3, inputs=SUBTRACTED)
    seen = []
    for b in range(len(ds)):
        batch = ds[b]
        seen += batch["index"].tolist()
        np.testing.assert_allclose(batch["x"][:, 0].numpy(), ref[batch["index"].numpy()], atol=tol)
    assert sorted(seen) == list(range(5))
    import h5py

    with h5py.File(path) as fh:
        light = ShardLightModels(path, fh)
        assert len(light) == 5
        np.testing.assert_array_equal(light[1:3], model[1:3])


def test_a_shard_without_the_fit_is_refused_with_the_key_named(tmp_path, lenses):
    path = _shard(tmp_path / "bare.h5", lenses[0])
    with pytest.raises(ValueError, match=rf"{LIGHT_FIT_GROUP}/mag missing.*simulation.light_fit"):
        ShardBatches([path], 5, (0.0, 1.0), inputs=SUBTRACTED)
    # other transforms read it
    assert len(ShardBatches([path], 5, (0.0, 1.0), inputs=SNR)) == 1


def test_whitening_is_measured_after_the_transform_and_records_it(tmp_path, lenses):
    images, fit = lenses
    path = _shard(tmp_path / "s.h5", images, fit)
    res = compute_whitening([path], tmp_path / "w.json", inputs=SNR)
    x = SNR.apply(images).astype(np.float64)
    assert res["mean"] == pytest.approx(x.mean(), rel=1e-6)
    assert res["std"] == pytest.approx(x.std(), rel=1e-5)
    assert read_inputs(tmp_path / "w.json") == SNR
    sub = compute_whitening([path], tmp_path / "w2.json", inputs=SUBTRACTED)
    assert abs(sub["mean"]) < 0.05 * res["mean"] * SIGMA_BG


def test_config_keys_choose_the_transform_and_the_fit():
    from pathlib import Path

    from subslope.config import cross_key_problems, light_fit_enabled, load
    from subslope.stages.train import input_transform

    config = load(Path(__file__).resolve().parents[1] / "config" / "tiny.yaml", env=False)
    assert config["training"]["inputs"] == "light_subtracted" and light_fit_enabled(config)
    assert input_transform(config).kind == "light_subtracted"
    config["simulation"]["light_fit"] = False
    assert any("simulation.light_fit" in p for p in cross_key_problems(config))
    config["training"]["inputs"] = "snr"
    assert not light_fit_enabled(config)
    snr = input_transform(config)
    assert snr.background_sigma > 0 and snr.exposure_time > 0
