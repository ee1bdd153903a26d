"""Domain check (subslope.validation.domain, subslope.stages.domain, subslope domain-check)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from subslope.validation.domain import (
    STATISTICS,
    border_level,
    compact_objects,
    domain_percentiles,
    image_statistics,
    noise_lag1,
    spread_table,
)

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.usefixtures("one_thread")


def test_percentiles_count_ties_half_and_flag_the_statistics_outside():
    sim = pd.DataFrame({"a": np.arange(100.0), "b": np.r_[np.zeros(50), np.ones(50)]})
    real = pd.DataFrame({"a": [-1.0, 10.0, 200.0, np.nan], "b": [0.0, 1.0, 0.5, 0.0]})
    table = domain_percentiles(sim, real, ["w", "x", "y", "z"], statistics=("a", "b"))
    np.testing.assert_allclose(table["a_pct"][:3], [0.0, 10.5, 100.0])
    np.testing.assert_allclose(table["b_pct"], [25.0, 75.0, 50.0, 25.0])
    assert table["inside"].tolist() == [False, True, False, False]
    assert table["outside"].tolist() == ["a", "", "a", "a"]  # NaN is never inside


def test_statistics_of_simulated_lenses_are_finite_and_as_defined(data_dir):
    import torch

    from subslope import config as cfgmod
    from subslope.physics.grid import pixel_grid
    from subslope.physics.instrument import add_noise
    from subslope.render.pipeline import RenderSettings, render
    from subslope.simulation.macro import sample_macro
    from subslope.simulation.observing import build_instrument, build_psf
    from subslope.simulation.scenes import Scene

    cfg = cfgmod.validate({"data": {"resources_dir": str(data_dir)}})
    psf, inst = build_psf(cfg), build_instrument(cfg)
    scene = Scene.from_config(
        "train",
        {
            "lens_light": {"prior": "hst_joint"},
            "source": {"kind": "sersic"},
            "components": {"subhalos": False, "los": False, "sky": True},
            "sky": {"level": {"dist": "uniform", "low": 0.05, "high": 0.2}},
        },
    )
    macro = sample_macro(scene, 4, np.random.default_rng(2))
    s = RenderSettings(device="cpu", dtype=torch.float64, compile="off")
    images = add_noise(render(macro, torch.as_tensor(psf), s), 3, instrument=inst).numpy()
    stats = image_statistics(
        images,
        macro["theta_e"],
        psf=psf,
        background_sigma=inst.background_sigma,
        exposure_time=inst.total_exposure_time,
        whitening=(float(images.mean()), float(images.std())),
        pixel_scale=0.04,
    )
    assert list(stats.columns) == ["lens_x", "lens_y", *STATISTICS]
    assert np.all(np.isfinite(stats[list(STATISTICS)].to_numpy()))
    xs, ys = (a.numpy() for a in pixel_grid(100, 0.04))
    k = 1
    r = np.hypot(xs - stats["lens_x"][k], ys - stats["lens_y"][k])
    assert stats["flux_centre"][k] == pytest.approx(images[k][r <= 0.3].sum())
    # the measured centre is the lens's, the fitted magnitude near the drawn one
    np.testing.assert_allclose(stats["lens_x"], macro["lens_x"], atol=0.03)
    assert np.median(np.abs(stats["light_mag"] - macro["light_mag"])) < 0.3
    assert np.all((stats["bright_fraction"] >= 0) & (stats["bright_fraction"] <= 1))
    # the border holds the sky level and the wings of the lens light
    excess = stats["border_level"].to_numpy() - macro["sky_level"]
    assert np.all(excess > -0.005) and np.min(excess) < 0.005


def test_noise_lag1_reads_the_pixel_correlation_and_not_smooth_light():
    import torch

    from subslope.physics.instrument import correlate_noise

    white = torch.randn(
        40, 100, 100, generator=torch.Generator().manual_seed(0), dtype=torch.float64
    )
    region = np.ones((40, 100, 100), dtype=bool)
    region[:, 30:70, 30:70] = False
    y, x = np.mgrid[:100, :100]
    smooth = 3.0 * np.exp(-((x - 20.0) ** 2 + (y - 80.0) ** 2) / (2 * 8.0**2))  # residual light
    values = {}
    for rho in (0.0, 0.3, 0.4, 0.5):
        noise = correlate_noise(white, rho).numpy()
        values[rho] = noise_lag1(noise + smooth, region)
        assert np.isfinite(values[rho]).all()
    np.testing.assert_allclose(np.median(values[0.0]), -0.037, atol=0.01)
    np.testing.assert_allclose(np.median(values[0.4]), 0.268, atol=0.015)
    medians = [np.median(values[r]) for r in (0.0, 0.3, 0.4, 0.5)]
    assert np.all(np.diff(medians) > 0.03)
    assert np.isnan(noise_lag1(white[:1].numpy(), np.zeros((1, 100, 100), dtype=bool))).all()


def test_border_level_is_the_clipped_median_of_the_frame():
    rng = np.random.default_rng(0)
    images = rng.normal(0.1, 0.01, (2, 60, 60))
    images[1] += 0.05
    images[:, 20:40, 20:40] += 5.0  # a galaxy inside the frame is not counted
    images[0, 1, 1] = 100.0  # nor a hot pixel on it
    np.testing.assert_allclose(border_level(images), [0.1, 0.15], atol=2e-3)


def test_compact_objects_are_masked_and_arcs_are_not():
    snr = np.zeros((1, 50, 50))
    snr[0, 10:12, 10:12] = 20.0  # a 4-pixel companion core
    snr[0, 30, 5:45] = 8.0  # a 40-pixel arc
    mask = compact_objects(snr)[0]
    assert mask[10, 10] and mask[8, 8] and not mask[7, 7]  # dilated by 2
    assert not mask[30, 20]
    assert not compact_objects(np.zeros((1, 10, 10))).any()


def test_spread_table_is_the_simulated_width_over_the_real_one():
    sim = pd.DataFrame({"a": np.linspace(0.0, 100.0, 1001)})
    real = pd.DataFrame({"a": [40.0, 50.0, np.nan]})
    t = spread_table(sim, real, statistics=("a",))
    row = t.iloc[0]
    assert row["sim_lo"] == pytest.approx(1.0) and row["sim_hi"] == pytest.approx(99.0)
    assert row["hst_min"] == 40.0 and row["width_ratio"] == pytest.approx(9.8)


@pytest.mark.slow
def test_domain_check_command_writes_the_table_and_figures(tmp_path, data_dir):
    import yaml

    from subslope.cli import main

    cfg = yaml.safe_load((REPO / "config" / "tiny.yaml").read_text())
    cfg = {
        **cfg,
        "base": str(REPO / "config" / "config.yaml"),
        "data": {"resources_dir": str(data_dir), "mirror": str(data_dir)},
        "simulation": {
            **cfg.get("simulation", {}),
            "render": {"compile": "off", "device": "cpu", "batch_images": 2},
        },
    }
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out = tmp_path / "out"
    assert main(["domain-check", "--config", str(path), "--n", "4", "--out", str(out)]) == 0
    table = pd.read_csv(out / "domain_check.csv")
    assert len(table) == 13 and {"system", "inside", "outside"} <= set(table.columns)
    assert all(f"{s}_pct" in table.columns for s in STATISTICS)
    for name in (
        "domain_check.png",
        "domain_gallery.png",
        "statistics.csv",
        "sources.csv",
        "spread.csv",
        "source_cleaning.png",
    ):
        assert (out / name).is_file(), name
