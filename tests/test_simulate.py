"""The forward simulator: shards from the tiny config, reproducibility, rerendering,
and the LoS profile parameters."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch
from scipy import stats

from subslope import config as cfgmod
from subslope import plan
from subslope.io import shards
from subslope.physics import concentration, cosmology
from subslope.physics.grid import pixel_grid
from subslope.simulation import los_halos as losmod
from subslope.simulation import rerender
from subslope.simulation import shard as simulate
from subslope.simulation.macro import sample_macro
from subslope.simulation.precision import SUBHALO_DTYPES
from subslope.simulation.scenes import Scene
from tests.conftest import REPO_ROOT


@pytest.fixture(scope="module")
def config(tmp_path_factory):
    from tests.conftest import shared_data_dir

    data = shared_data_dir()
    if not (data / "cosmos").is_dir():
        pytest.skip(f"no data mirror at {data}")
    cfg = cfgmod.load(REPO_ROOT / "config" / "tiny.yaml", env=False)
    cfg["data"]["resources_dir"] = str(data)
    return cfg


@pytest.fixture(scope="module")
def train_shard(config, tmp_path_factory):
    return simulate.simulate_shard(
        config, "train", 0, tmp_path_factory.mktemp("sim") / "a.h5", progress=False
    )


def test_shard_layout(train_shard):
    with shards.open_shard(train_shard) as s:
        n = len(s)
        assert s.images.shape == (n, 100, 100) and n == 3
        for key in (
            "gamma_sub",
            "theta_e",
            "lens_x",
            "lens_y",
            "set_index",
            "n_sub",
            "delta_los",
            "noise_seed",
        ):
            assert s.params[key].shape == (n,), key
        assert "c_multiplier" not in s.params
        assert set(s.sources) == {"ident", "z_phot", "pixel_scale", "mag"}  # renormalised
        assert s.subhalos["counts"].sum() == s.params["n_sub"].sum() == s.subhalos["mass"].size
        assert s.los["counts"].sum() == s.los["z"].size
        # drawn fields at their stored precision, heaviest first; amplitudes derived on reading
        assert {k: v.dtype for k, v in s.subhalos.items() if k != "counts"} == {
            k: np.dtype(SUBHALO_DTYPES[k]) for k in ("mass", "x", "y", "gamma", "e1", "e2")
        }
        assert all(v.dtype == np.float32 for k, v in s.los.items() if k != "counts")
        first = s.subhalos["mass"][: s.subhalos["counts"][0]]
        assert np.all(np.diff(first) <= 0)
        a = s.attrs
        assert a["scene"] == "train" and a["n_images"] == n and len(a["config_hash"]) == 64
        assert a["seed_spawn_key"][0] == simulate.scene_id("train") and a["seed_spawn_key"][1] == 0
        assert a["render_settings"]["dtype"] == "float32" and a["subhalo_profile"] == "epl"
        assert np.all(np.isfinite(s.images[()]))


def test_same_seed_byte_identical_and_shards_differ(config, train_shard, tmp_path):
    again = simulate.simulate_shard(config, "train", 0, tmp_path / "b.h5", progress=False)
    assert shards.file_sha256(again) == shards.file_sha256(train_shard)
    other = simulate.simulate_shard(config, "train", 1, tmp_path / "c.h5", progress=False)
    with shards.open_shard(train_shard) as a, shards.open_shard(other) as b:
        assert not np.array_equal(a.images[()], b.images[()])
        assert not np.array_equal(a.params["theta_e"], b.params["theta_e"])
        assert a.attrs["config_hash"] == b.attrs["config_hash"]


def test_refuses_overwrite(config, train_shard):
    before = shards.file_sha256(train_shard)
    with pytest.raises(FileExistsError, match=str(train_shard.name)):
        simulate.simulate_shard(config, "train", 0, train_shard, progress=False)
    assert shards.file_sha256(train_shard) == before


def test_rerender_bit_for_bit(config, train_shard):
    with shards.open_shard(train_shard) as s:
        stored = s.images[()]
        seeds = s.params["noise_seed"]
    for i in range(stored.shape[0]):
        np.testing.assert_array_equal(rerender.rerender(train_shard, i), stored[i])
    # noise-free: the same clean image as the simulator's own noise-free path
    ss = simulate.shard_seed_sequence(config["seed"], "train", 0)
    clean = simulate.simulate_images(config, "train", 3, ss, noise=False)
    np.testing.assert_array_equal(clean["params"]["noise_seed"], seeds)
    for i in range(3):
        np.testing.assert_array_equal(
            rerender.rerender(train_shard, i, noise=False), clean["images"][i]
        )
    assert not np.array_equal(clean["images"][0], stored[0])


def test_subhalo_sheet_kappa_is_the_renderers_sheet(config, train_shard):
    """The diagnostic sheet κ of a stored image equals the κ the renderer's population
    pass gives the same members on the pixel centres (float64, direct sums), and the
    strided mean is close to it."""
    from subslope.render.kernels import kernels_for
    from subslope.render.populations import pack_population, population_pass

    with shards.open_shard(train_shard) as s:
        n = len(s)
        inp = rerender.stored_inputs(s, np.arange(n))
        npix = s.images.shape[-1]
    subs = inp["subhalos"]
    settings = dataclasses.replace(
        inp["settings"], dtype=torch.float64, compile="off", population="direct"
    )
    both = rerender.sheet_kappas(train_shard, np.arange(n), stride=1)
    kappa = both["subhalos"]
    los_counts = inp["los"].counts if inp["los"] is not None else np.zeros(n, int)
    assert np.all((both["los"] < 0) == (np.asarray(los_counts) > 0))
    coarse = rerender.sheet_kappas(train_shard, np.arange(n), stride=4)["subhalos"]
    x, y = pixel_grid(npix, settings.pixel_scale, dtype=torch.float64)
    x, y = x.reshape(1, -1), y.reshape(1, -1)
    first = np.concatenate([[0], np.cumsum(subs.counts)])
    assert subs.counts.max() > 0
    for j in range(n):
        if subs.counts[j] == 0:
            assert kappa[j] == 0.0
            continue
        sel = slice(first[j], first[j + 1])
        flat = {
            k: np.asarray(getattr(subs, k))[sel] for k in ("amp", "gamma", "e1", "e2", "x", "y")
        }
        pop = pack_population(
            "epl", flat, subs.counts[j : j + 1], settings.n_terms, torch.float64, "cpu"
        )
        kern = kernels_for(settings, torch.device("cpu"))
        _, _, k_sheet = population_pass(pop, x, y, settings, kern, npix * npix)
        assert kappa[j] < 0 and kappa[j] == pytest.approx(float(k_sheet), rel=1e-9)
        assert coarse[j] == pytest.approx(kappa[j], rel=0.1)


def stored_units(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a − b| in units of the last stored place (16-bit mantissa) of the larger."""
    big = np.maximum(np.abs(a), np.abs(b)).astype(np.float64)
    unit = np.exp2(np.floor(np.log2(np.where(big > 0, big, 1.0))) - 16)
    return np.abs(a.astype(np.float64) - b) / unit


def test_batch_size_changes_images_at_rounding_only(config, train_shard):
    cfg = copy.deepcopy(config)
    cfg["simulation"]["render"]["batch_images"] = 3
    out, again = (
        simulate.simulate_images(
            cfg, "train", 3, simulate.shard_seed_sequence(cfg["seed"], "train", 0), noise=False
        )
        for _ in range(2)
    )
    np.testing.assert_array_equal(out["images"], again["images"])  # same batch: same bits
    clean = np.stack([rerender.rerender(train_shard, i, noise=False) for i in range(3)])
    assert stored_units(out["images"], clean).max() <= 1.0


@pytest.mark.parametrize(
    "scene", ["train", "validation", "test_epl", "nfw", "tnfw", "null_nosub", "null_nosub_los"]
)
def test_rerender_contract(config, scene, tmp_path):
    """With its batch: the stored image bit for bit; alone: the noise-free image to one
    unit in the last stored place."""
    mult = 1.0 if scene in ("nfw", "tnfw") else None
    path = simulate.simulate_shard(
        config, scene, 0, tmp_path / "s.h5", multiplier=mult, progress=False
    )
    with shards.open_shard(path) as s:
        stored, n = s.images[()], len(s)
        assert s.attrs["render_settings"]["batch_images"] == 2 and n > 2
    for i in range(n):
        np.testing.assert_array_equal(rerender.rerender(path, i), stored[i])
        batch = rerender.rerender(path, i, noise=False)
        alone = rerender.rerender(path, i, noise=False, alone=True)
        assert stored_units(alone, batch).max() <= 1.0
    with pytest.raises(ValueError, match="noise=False"):
        rerender.rerender(path, 0, alone=True)


@pytest.mark.parametrize("scene", ["nfw", "tnfw"])
def test_cdm_shards(config, scene, tmp_path):
    with pytest.raises(ValueError, match="multiplier"):
        simulate.simulate_shard(config, scene, 0, tmp_path / "x.h5", progress=False)
    path = simulate.simulate_shard(
        config, scene, 0, tmp_path / "s.h5", multiplier=1.0, progress=False
    )
    with shards.open_shard(path) as s:
        assert "gamma_sub" not in s.params and np.all(s.params["c_multiplier"] == 1.0)
        assert s.attrs["subhalo_profile"] == scene and s.attrs["los_profile"] == "nfw"
        assert {"mass", "c200", "x", "y"} == set(s.subhalos) - {"counts"}  # r_s, r_t derived
        assert "c200" in s.los and "amp" not in s.los
        assert s.attrs["multiplier"] == 1.0 and len(s.attrs["seed_spawn_key"]) == 2
    np.testing.assert_array_equal(rerender.rerender(path, 1), shards.open_shard(path).images[1])
    # every multiplier draws the same sets: only the concentrations differ, by the factor a
    grid = copy.deepcopy(config)
    grid["simulation"]["multipliers"] = [1.0, 4.0]
    other = simulate.simulate_shard(
        grid, scene, 0, tmp_path / "a4.h5", multiplier=4.0, progress=False
    )
    with shards.open_shard(path) as s, shards.open_shard(other) as t:
        for key in set(s.params) - {"c_multiplier"}:
            np.testing.assert_array_equal(s.params[key][()], t.params[key][()], err_msg=key)
        for key in ("counts", "mass", "x", "y"):
            np.testing.assert_array_equal(s.subhalos[key][()], t.subhalos[key][()])
        np.testing.assert_allclose(t.subhalos["c200"][()], 4.0 * s.subhalos["c200"][()], rtol=1e-6)
        for key in set(s.los):
            np.testing.assert_array_equal(s.los[key][()], t.los[key][()], err_msg=key)
        assert np.all(t.params["c_multiplier"][()] == 4.0)
        assert not np.array_equal(s.images[()], t.images[()])


def test_nfw_and_tnfw_draw_the_same_sets(config, tmp_path):
    paths = {
        scene: simulate.simulate_shard(
            config, scene, 0, tmp_path / f"{scene}.h5", multiplier=1.0, progress=False
        )
        for scene in ("nfw", "tnfw")
    }
    with shards.open_shard(paths["nfw"]) as s, shards.open_shard(paths["tnfw"]) as t:
        for key in s.params:
            np.testing.assert_array_equal(s.params[key][()], t.params[key][()], err_msg=key)
        for key in ("counts", "mass", "x", "y", "c200"):
            np.testing.assert_array_equal(s.subhalos[key][()], t.subhalos[key][()])
        assert (s.attrs["subhalo_profile"], t.attrs["subhalo_profile"]) == ("nfw", "tnfw")
        assert not np.array_equal(s.images[()], t.images[()])


def test_subhalo_free_images_remove_the_subhalos_and_nothing_else(config, tmp_path):
    """A scene without subhalos re-renders to its stored images bit for bit (same
    batches); in a CDM scene removing the subhalos changes the images, and keeping the
    line-of-sight halos tells the re-render from the halo-free one."""
    empty = simulate.simulate_shard(config, "null_nosub_los", 0, tmp_path / "n.h5", progress=False)
    with shards.open_shard(empty) as s:
        stored, n = s.images[()], len(s)
    np.testing.assert_array_equal(rerender.subhalo_free_images(empty, range(n), chunk=2), stored)
    path = simulate.simulate_shard(
        config, "nfw", 0, tmp_path / "c.h5", multiplier=1.0, progress=False
    )
    with shards.open_shard(path) as s:
        stored, n = s.images[()], len(s)
        has_subhalos = np.asarray(s.subhalos["counts"]) > 0
    removed = rerender.subhalo_free_images(path, range(n), chunk=2)
    halo_free = rerender.halo_free_images(path, range(n), keep_sheets=False, chunk=2)
    assert removed.shape == stored.shape and np.all(np.isfinite(removed))
    assert has_subhalos.any()
    for i in np.flatnonzero(has_subhalos):
        assert stored_units(removed[i], stored[i]).max() > 1.0
        assert stored_units(removed[i], halo_free[i]).max() > 1.0


def test_shard_jobs_and_paths(config):
    full = cfgmod.validate({})
    jobs = plan.shard_jobs(full)
    per_scene = {}
    for j in jobs:
        per_scene[j["scene"]] = per_scene.get(j["scene"], 0) + 1
    assert per_scene == {"train": 2, "validation": 1, "test_epl": 1, "nfw": 2, "tnfw": 2}
    assert plan.shard_path("nfw", 3, 0.5) == "results/simulate_shard/nfw/a0.5/shard_3.h5"
    assert plan.shard_path("train", 1) == "results/simulate_shard/train/shard_1.h5"
    bad = {"simulation": {"scenes": {"test_epl": {"n_shards": 1, "images_per_shard": 10}}}}
    with pytest.raises(cfgmod.ConfigError, match="simulation.scenes.test_epl.images_per_shard"):
        plan.shard_jobs(bad)


def test_seed_streams_are_distinct():
    a = simulate.shard_seed_sequence(1, "train", 0).generate_state(4)
    assert not np.array_equal(a, simulate.shard_seed_sequence(1, "train", 1).generate_state(4))
    assert not np.array_equal(a, simulate.shard_seed_sequence(1, "validation", 0).generate_state(4))
    assert not np.array_equal(a, simulate.shard_seed_sequence(2, "train", 0).generate_state(4))
    assert simulate.scene_id("train") == simulate.scene_id("train") < 2**64


# ---------------------------------------------------------------------------- LoS profiles
def _los_draw(scene, n, rng, multiplier=None):
    macro = sample_macro(scene, n, rng, multiplier=multiplier)
    macro["delta_los"] = np.full(n, 2.0)
    batch = losmod.sample_los_batch(
        macro["z_lens"],
        macro["z_source"],
        macro["theta_e"],
        macro["gamma_ml"],
        macro["delta_los"],
        rng,
    )
    return macro, batch


def test_los_epl_profiles(rng):
    scene = Scene.from_config("train", {"subhalos": {"gamma": {"dist": "fixed", "value": 1.2}}})
    macro, batch = _los_draw(scene, 40, rng)
    pop = losmod.los_profiles(batch, scene, macro, rng)
    assert pop.profile == "epl" and pop.counts.sum() > 100
    assert np.all((pop.gamma >= 1.01) & (pop.gamma <= 2.99)) and pop.gamma.min() < 1.1
    # truncated normal N(1.2, 0.12) on [1.01, 2.99]
    a = (1.01 - 1.2) / 0.12
    ks = stats.kstest(pop.gamma, stats.truncnorm(a, (2.99 - 1.2) / 0.12, loc=1.2, scale=0.12).cdf)
    assert ks.pvalue > 1e-3
    sys = np.repeat(np.arange(40), pop.counts)
    for k in np.flatnonzero(pop.counts)[:3]:
        j = np.flatnonzero(sys == k)[0]
        expect = cosmology.epl_amp_from_m200(
            pop.m200[j], pop.gamma[j], pop.z[j], macro["z_source"][k]
        )
        assert pop.amp[j] == pytest.approx(float(expect), rel=1e-12)
    assert np.all(np.abs(pop.e1) <= 0.2) and pop.c200 is None
    with pytest.raises(ValueError, match="gamma_sub"):
        losmod.los_profiles(batch, scene, {"z_source": macro["z_source"]}, rng)


@pytest.mark.parametrize("apply_to_los", [False, True])
def test_los_nfw_concentrations(rng, apply_to_los):
    scene = Scene.from_config("nfw", {"concentration": {"apply_to_los": apply_to_los}})
    macro, batch = _los_draw(scene, 39, rng, multiplier=4.0)
    pop = losmod.los_profiles(batch, scene, macro, rng)
    assert pop.profile == "nfw" and pop.amp is None and pop.counts.sum() > 100
    ratio = np.log10(pop.c200 / concentration.dutton_maccio_c200(pop.m200, pop.z))
    shift = np.log10(4.0) if apply_to_los else 0.0
    assert np.mean(ratio) - shift == pytest.approx(0.0, abs=0.03)
    assert np.std(ratio) == pytest.approx(0.1, rel=0.2)
    sys = np.repeat(np.arange(39), pop.counts)
    j = int(np.flatnonzero(pop.counts > 0)[0])
    i = np.flatnonzero(sys == j)[0]
    r_s, alpha = cosmology.nfw_params_from_m200_c(
        pop.m200[i], pop.c200[i], pop.z[i], macro["z_source"][j]
    )
    assert pop.r_s[i] == pytest.approx(float(r_s), rel=1e-12) and pop.alpha_rs[i] == pytest.approx(
        float(alpha), rel=1e-12
    )


def test_a_new_stage_changes_no_shard_job_param(tmp_path):
    """The shard jobs' Snakemake params leave the stage flags out: adding a stage (or
    switching one) reruns no shard."""
    from subslope import config as cfgmod
    from subslope.plan import shard_job_config, with_stages_off

    config = cfgmod.load(REPO_ROOT / "config" / "tiny.yaml", env=False)
    job = shard_job_config(config, "train")
    param = {k: v for k, v in job.items() if k != "stages"}
    off = cfgmod.validate({**config, "stages": {**config["stages"], "hst": False}})
    assert {k: v for k, v in shard_job_config(off, "train").items() if k != "stages"} == param
    assert with_stages_off(param) == job
    # the workflow's param is the same (subslope.campaigns.targets, bound in common.smk)
    from subslope.campaigns.targets import Targets

    class Wildcards(dict):
        scene = "train"

    assert Targets(config).shard_job(Wildcards()) == param == Targets(off).shard_job(Wildcards())
