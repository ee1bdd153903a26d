"""Figure 4's second grid and what it is read against: the `landing` placement, the
matched EPL controls on common draws, the abundance count of a CDM host, and the
concentration contrast of an ideal observer."""

from __future__ import annotations

import copy

import numpy as np
import pandas as pd
import pytest
import torch
from scipy import integrate

from subslope import config as cfgmod
from subslope.io import shards
from subslope.physics.abundance import expected_count, field_area_kpc2, uniform_count_max
from subslope.physics.cosmology import arcsec_to_mpc
from subslope.render.pipeline import RenderSettings, render_smooth
from subslope.simulation import shard as simulate
from subslope.simulation.macro import sample_macro
from subslope.simulation.observing import build_psf
from subslope.simulation.resolve import resolved_scene
from subslope.simulation.scenes import Scene, SceneError
from subslope.simulation.sources import draw_sources, landing_stamps, pixelated_sources
from subslope.simulation.subhalos import arc_candidates
from subslope.stages.cdm_grid import control_slope
from subslope.stages.signal_budget import contrast_rows
from tests.conftest import REPO_ROOT


@pytest.fixture(scope="module")
def config():
    from tests.conftest import shared_data_dir

    data = shared_data_dir()
    if not (data / "cosmos").is_dir():
        pytest.skip(f"no data mirror at {data}")
    cfg = cfgmod.load(REPO_ROOT / "config" / "tiny.yaml", env=False)
    cfg["data"]["resources_dir"] = str(data)
    return cfgmod.validate(cfg)


# ----------------------------------------------------------------------------- placement
def test_landing_subhalos_sit_where_the_stamp_lands(config, tmp_path):
    """Every subhalo of a `landing` scene lies on a pixel of the image of its stamp's
    support above the threshold, and that support covers more than the galaxy."""
    path = simulate.simulate_shard(
        config, "nfw_ref", 0, tmp_path / "r.h5", multiplier=1.0, progress=False
    )
    sc, _ = resolved_scene(config, "nfw_ref")
    n = 4
    macro = sample_macro(sc, n, np.random.default_rng(0), multiplier=1.0)
    zp = float(config["instrument"]["zero_point"])
    sources, stamps, pad = draw_sources(config, sc, macro, np.random.default_rng(1), zp)
    settings = RenderSettings(device="cpu", dtype=torch.float64, compile="off")
    psf = torch.as_tensor(build_psf(config), dtype=torch.float64)
    land = render_smooth(
        macro,
        psf,
        settings,
        sources=pixelated_sources(landing_stamps(stamps), sources["pixel_scale"], pad, settings),
    ).numpy()
    galaxy = render_smooth(
        macro,
        psf,
        settings,
        sources=pixelated_sources(stamps, sources["pixel_scale"], pad, settings),
    ).numpy()
    for b in range(n):
        on_land = arc_candidates(land[b], sc.subhalos.threshold_fraction)
        on_galaxy = arc_candidates(galaxy[b], 0.2)
        assert set(on_galaxy) <= set(on_land) and on_land.size > on_galaxy.size
    with shards.open_shard(path) as s:
        assert s.attrs["scene_spec"]["subhalos"]["placement"] == "landing"
        counts = np.asarray(s.subhalos["counts"])
        assert counts.sum() > 0
        x, y = np.asarray(s.subhalos["x"]), np.asarray(s.subhalos["y"])
    half = 0.5 * config["instrument"]["npix"] * config["instrument"]["pixel_scale"]
    assert np.all(np.abs(x) <= half) and np.all(np.abs(y) <= half)


def test_landing_needs_a_stamp():
    spec = {"source": {"kind": "sersic"}, "subhalos": {"placement": "landing"}}
    with pytest.raises(SceneError, match="landing.*COSMOS"):
        Scene.from_config("x", spec)


def test_fixed_gamma_needs_epl_subhalos_inside_the_bounds():
    with pytest.raises(SceneError, match="fixed_gamma.*EPL"):
        Scene.from_config("x", {"subhalos": {"profile": "nfw", "fixed_gamma": 2.0}})
    with pytest.raises(SceneError, match="fixed_gamma"):
        Scene.from_config("x", {"subhalos": {"fixed_gamma": 3.5}})
    sc = Scene.from_config("x", {"common_draws": True, "subhalos": {"fixed_gamma": 1.8}})
    assert sc.common_draws and sc.subhalos.fixed_gamma == 1.8
    # absent keys stay out of the scene's mapping (no existing shard's hash moves)
    from subslope.simulation.presets import merge_onto_preset

    assert "common_draws" not in merge_onto_preset("train", {}, "scenes.train")


# ----------------------------------------------------------------------------- controls
def test_a_matched_control_draws_the_cdm_sets(config, tmp_path):
    """A control (common_draws, fixed_gamma) holds the CDM shard's lenses, sources, noise
    seeds, LoS halos, subhalo counts and masses; only its label and profiles differ."""
    cdm = simulate.simulate_shard(
        config, "nfw", 0, tmp_path / "c.h5", multiplier=1.0, progress=False
    )
    ctl = simulate.simulate_shard(config, "epl_control_15", 0, tmp_path / "e.h5", progress=False)
    assert simulate.draws_name(config, "epl_control_15", None) == simulate.CDM_DRAWS
    assert simulate.draws_name(config, "test_epl", None) == "test_epl"
    with shards.open_shard(cdm) as s, shards.open_shard(ctl) as t:
        for key in set(s.params) - {"c_multiplier"}:
            np.testing.assert_array_equal(s.params[key][()], t.params[key][()], err_msg=key)
        np.testing.assert_array_equal(t.params["gamma_sub"][()], 1.5)
        for key in ("counts", "mass"):
            np.testing.assert_array_equal(s.subhalos[key][()], t.subhalos[key][()])
        for key in s.los:
            np.testing.assert_array_equal(s.los[key][()], t.los[key][()], err_msg=key)
        assert t.attrs["subhalo_profile"] == "epl"


def test_control_slope_maps_a_reading_only_where_the_controls_rise():
    rising = pd.DataFrame(
        {"grid": "field", "gamma": [1.5, 1.8, 2.1, 2.4], "median": [1.6, 1.7, 1.9, 2.3]}
    )
    assert control_slope(rising, "field", 1.8) == pytest.approx(1.95)
    assert control_slope(rising, "field", 1.2) is None  # below the lowest control
    assert control_slope(rising, "reference", 1.8) is None  # no controls of that grid
    flat = rising.assign(median=[1.6, 1.6, 1.7, 1.65])
    assert control_slope(flat, "field", 1.62) is None


def test_control_and_abundance_keys_are_checked():
    """Missing scenes are named when the config is validated, what needs the scenes
    resolved when the run is planned; both name the key."""
    from subslope.plan import plan_problems

    base = cfgmod.load(REPO_ROOT / "config" / "tiny.yaml", env=False)

    def problems(**cdm) -> str:
        bad = copy.deepcopy(base)
        bad["cdm"].update(cdm)
        try:
            return "\n".join(plan_problems(bad))
        except cfgmod.ConfigError as err:
            return str(err)

    text = problems(field_controls=["test_epl"])
    assert "cdm.field_controls[0] = 'test_epl'" in text and "fixed_gamma" in text
    text = problems(abundance=["test_epl"])
    assert "cdm.abundance[0] = 'test_epl'" in text and "NFW or tNFW" in text
    text = problems(abundance=["no_such_scene"])
    assert "cdm.abundance[0] = 'no_such_scene': no shards of that scene" in text
    text = problems(reference_nfw_scene=None, reference_tnfw_scene=None)
    assert "reference grid is off" in text
    assert problems() == ""


# ----------------------------------------------------------------------------- abundance
def test_expected_count_is_the_integral_of_the_mass_function():
    sigma, area, slope, pivot = 2e-3, 150.0, -1.9, 1e10
    direct, _ = integrate.quad(
        lambda m: sigma / pivot * (m / pivot) ** slope * area, 1e7, 1e10, limit=200
    )
    assert expected_count(sigma, area, slope=slope) == pytest.approx(direct, rel=1e-8)
    # pyHalo's pivot of 1e8 Msun: the same integral, other normalisation
    direct8, _ = integrate.quad(lambda m: 0.02 / 1e8 * (m / 1e8) ** slope * area, 1e7, 1e10)
    assert expected_count(0.02, area, m_pivot=1e8) == pytest.approx(direct8, rel=1e-8)
    with pytest.raises(ValueError):
        expected_count(sigma, area, slope=-1.0)


def test_a_cdm_host_projects_a_few_hundred_subhalos_into_the_field():
    side_kpc = 1e3 * float(arcsec_to_mpc(0.2)) * 4.0
    assert float(field_area_kpc2(4.0, 0.2)) == pytest.approx(side_kpc**2)
    lo, mid, hi = uniform_count_max(0.2, 4.0)
    assert lo < mid < hi and 300 < mid < 500  # mean count N_max / 2 of ~200
    assert mid == pytest.approx(2 * float(expected_count(2e-3, side_kpc**2)))


# ----------------------------------------------------------------------------- contrast
def test_the_contrast_of_a_draw_with_itself_is_zero_and_grows_with_a(config, tmp_path):
    grid = copy.deepcopy(config)
    grid["simulation"]["multipliers"] = [1.0, 8.0]
    low = simulate.simulate_shard(
        grid, "nfw", 0, tmp_path / "a1.h5", multiplier=1.0, progress=False
    )
    high = simulate.simulate_shard(
        grid, "nfw", 0, tmp_path / "a8.h5", multiplier=8.0, progress=False
    )
    kw = {"mask_factor": 1.5, "scene": "nfw", "iterations": 2}
    same = contrast_rows(low, low, 2, multipliers=(1.0, 1.0), **kw)
    assert all(r["dchi2_fixed"] == 0.0 and r["dchi2_refit"] == 0.0 for r in same)
    rows = contrast_rows(low, high, 2, multipliers=(1.0, 8.0), **kw)
    with_subhalos = [r for r in rows if r["n_sub"] > 0]
    assert with_subhalos and all(r["dchi2_fixed"] > 0 for r in with_subhalos)
    assert all(0 <= r["dchi2_refit"] <= r["dchi2_fixed"] * (1 + 1e-9) for r in rows)
    other = simulate.simulate_shard(config, "test_epl", 0, tmp_path / "t.h5", progress=False)
    with pytest.raises(ValueError, match="common draws"):
        contrast_rows(low, other, 2, multipliers=(1.0, 8.0), **kw)


# ----------------------------------------------------------------------------- verdicts
def _grid_table(medians, half=0.1):
    a = [0.5, 1.0, 2.0, 4.0, 8.0]
    return pd.DataFrame(
        {
            "scene": "nfw",
            "multiplier": a,
            "median": medians,
            "lo": [m - half for m in medians],
            "hi": [m + half for m in medians],
        }
    )


def test_figure4_verdicts_follow_their_tables():
    from subslope.stages.cdm_grid import figure4_verdicts

    grids = {"field": ("nfw", "tnfw")}
    rising = pd.DataFrame({"grid": "field", "gamma": [1.5, 2.4], "median": [1.6, 2.2]})
    flat = rising.assign(median=[1.7, 1.7])
    contrast = pd.DataFrame({"scene": ["nfw"], "a_high": [8.0], "stack_refit": [300.0]})
    weak = contrast.assign(stack_refit=[0.3])
    up, level = _grid_table([1.6, 1.65, 1.8, 1.95, 2.1]), _grid_table([1.7] * 5)

    def verdict(table, **kw):
        return figure4_verdicts(table, grids, **kw)[0]["verdict"]

    assert verdict(up, control=rising, contrast=contrast) == "the estimator reads a"
    # a large oracle contrast and no network that finds it: undecided, never "cannot"
    assert verdict(level, control=rising, contrast=contrast).startswith("not settled")
    chance = {"nfw": 0.52}
    text = verdict(level, control=rising, contrast=contrast, classifier=chance)
    assert text.startswith("not settled") and "stack AUC 0.52" in text
    found = {"nfw": 0.9}
    assert verdict(level, control=rising, contrast=contrast, classifier=found).startswith(
        "the estimator misses what a direct classifier finds"
    )
    assert verdict(level, control=rising, contrast=weak).startswith("the images cannot")
    assert verdict(level, control=rising, contrast=weak, classifier=found).startswith(
        "the images cannot"
    )
    assert verdict(up, control=flat, contrast=contrast).startswith("no reading maps")
    assert verdict(up).startswith("not checked")  # no controls: never the favourable answer
    assert verdict(level, control=rising).startswith("not checked")
    row = figure4_verdicts(up, grids, control=rising)[0]
    assert row["rise"] == pytest.approx(0.45) and row["maps_to"] == pytest.approx(
        1.5 + 0.9 * 0.05 / 0.6
    )


def test_the_results_page_names_a_missing_figure4_table(tmp_path):
    from subslope.campaigns.results_page import verdicts

    (tmp_path / "cdm_prediction.csv").write_text(
        "scene,median,p16,p84,n_sets\nnfw,1.7,1.6,1.8,40\n"
    )
    assert any("Figure 4: not checked" in line for line in verdicts(tmp_path))
    (tmp_path / "figure4.csv").write_text(
        "grid,nfw_scene,verdict\nfield,nfw,the images cannot order a (ideal observer)\n"
    )
    assert any("field grid (nfw): the images cannot order a" in v for v in verdicts(tmp_path))


def test_multipliers_are_one_value_within_one_tolerance():
    from subslope.simulation.resolve import MULTIPLIER_RTOL, same_multiplier

    assert same_multiplier(8.0, 8.0 * (1 + MULTIPLIER_RTOL / 2))
    assert not same_multiplier(8.0, 8.0 * (1 + 10 * MULTIPLIER_RTOL))
    column = pd.Series([0.5, 1.0, 1.0 + 1e-12, 8.0])
    np.testing.assert_array_equal(same_multiplier(column, 1.0), [False, True, True, False])
    assert not same_multiplier(0.0, 1e-300)  # no absolute slack near zero
