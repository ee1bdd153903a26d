"""Tests of subslope.simulation.scenes: paper defaults, config errors, macro sampling."""

from __future__ import annotations

import math
from pathlib import Path

import jsonschema
import numpy as np
import pytest
import yaml
from scipy import stats

from subslope.simulation.macro import sample_macro
from subslope.simulation.priors import Normal, PriorError, Uniform, UniformInt
from subslope.simulation.scenes import PRESETS, Scene, SceneError, scenes_from_config  # noqa: F401

ROOT = Path(__file__).resolve().parents[1]
FRAGMENT = ROOT / "config" / "config.yaml"
SCHEMA_FRAGMENT = ROOT / "src" / "subslope" / "schemas" / "config.schema.yaml"

ALWAYS = {
    "z_lens",
    "z_source",
    "src_x",
    "src_y",
    "src_rotation",
    "lens_x",
    "lens_y",
    "theta_e",
    "lens_e1",
    "lens_e2",
    "gamma_ml",
    "set_index",
}


@pytest.fixture(scope="module")
def scenes():
    return scenes_from_config({})


def test_named_scenes_exist(scenes):
    assert {"train", "validation", "test_epl", "nfw", "tnfw"} <= set(scenes) == set(PRESETS)


def test_train_defaults_equal_paper_table(scenes):
    s = scenes["train"]
    assert s.redshifts.z_lens == Uniform(0.15, 0.25) and s.redshifts.z_source == Uniform(0.5, 0.7)
    assert (
        s.source.x == Uniform(-0.1, 0.1) and s.source.kind == "cosmos" and s.source.split == "train"
    )
    assert s.main_lens.x == Uniform(-0.2, 0.2)
    assert s.main_lens.theta_e == Uniform(0.9, 1.3)
    assert s.main_lens.e1 == Uniform(-0.2, 0.2)
    assert s.main_lens.gamma == Normal(2.0, 0.1, 1.1, 2.9)  # paper σ, not the code's 0.2
    assert s.multipoles.a3 == Uniform(0.0, 0.05) and s.multipoles.phi4 == Uniform(-math.pi, math.pi)
    assert s.shear.g1 == Uniform(-0.1, 0.1)
    assert s.lens_light.mag == Uniform(17.0, 19.0)  # paper, not U(16, 19)
    assert s.lens_light.n_sersic == Normal(2.0, 0.5, 0.5, 8.0)
    assert s.lens_light.r_sersic.loc == 0.8 and s.lens_light.r_sersic.std == 0.15
    assert s.lens_light.r_sersic.support[0] > 0
    assert s.lens_light.e2 == Uniform(-0.1, 0.1)
    sub = s.subhalos
    assert sub.count == UniformInt(0, 3000)
    assert (sub.mass.slope, sub.mass.low, sub.mass.high) == (-1.9, 1e7, 1e10)
    assert sub.gamma == Uniform(1.1, 2.9)
    assert sub.gamma_scatter == 0.1 and sub.gamma_bounds == (1.01, 2.99)
    assert sub.e1 == Uniform(-0.2, 0.2)
    assert (sub.profile, sub.placement, sub.threshold_fraction) == ("epl", "arc", 0.2)
    assert s.los.delta_los == Uniform(0.0, 2.0) and s.los.profile == "epl"
    assert s.images_per_set == 1 and s.has_label and not s.uses_concentration


def test_evaluation_and_cdm_presets(scenes):
    v, t = scenes["validation"], scenes["test_epl"]
    assert v.subhalos.count == UniformInt(0, 1800) and v.source.split == "validation"
    assert v.main_lens == scenes["train"].main_lens
    assert (
        t.images_per_set == 13
        and t.source.split == "test"
        and t.subhalos.count == UniformInt(0, 1800)
    )
    for name, prof in (("nfw", "nfw"), ("tnfw", "tnfw")):
        c = scenes[name]
        assert c.subhalos.profile == prof and c.subhalos.placement == "everywhere"
        assert c.los.profile == "nfw" and c.images_per_set == 13
        assert c.subhalos.count == UniformInt(0, 1800)
        assert c.concentration.scatter_dex == 0.1 and c.concentration.apply_to_los is False
        assert 1.0 in c.concentration.multipliers
        assert c.uses_concentration and not c.has_label


def test_overrides_merge_and_replace_priors():
    s = Scene.from_config(
        "train",
        {
            "main_lens": {
                "gamma": {"dist": "normal", "mean": 2.0, "std": 0.2, "low": 1.1, "high": 2.9}
            },
            "lens_light": {"mag": {"dist": "uniform", "low": 16.0, "high": 19.0}},
            "subhalos": {"threshold_fraction": 0.5},
        },
    )
    assert s.main_lens.gamma.std == 0.2 and s.main_lens.theta_e == Uniform(0.9, 1.3)
    assert s.lens_light.mag == Uniform(16.0, 19.0)
    assert s.subhalos.threshold_fraction == 0.5 and s.subhalos.count == UniformInt(0, 3000)
    custom = scenes_from_config({"mine": {"images_per_set": 4}})["mine"]
    assert custom.images_per_set == 4 and custom.subhalos.count == UniformInt(0, 3000)


@pytest.mark.parametrize(
    "spec, needle",
    [
        (
            {"main_lens": {"theta_e": {"dist": "uniform", "low": 1.3, "high": 0.9}}},
            "scenes.train.main_lens.theta_e.low",
        ),
        (
            {"main_lens": {"theta_e": {"dist": "uniform", "low": -1.0, "high": 0.9}}},
            "scenes.train.main_lens.theta_e",
        ),
        ({"main_lens": {"theta_ee": 1.0}}, "scenes.train.main_lens.theta_ee"),
        ({"subhalos": {"profile": "burkert"}}, "scenes.train.subhalos.profile"),
        ({"subhalos": {"placement": "ring"}}, "scenes.train.subhalos.placement"),
        ({"subhalos": {"threshold_fraction": 1.5}}, "scenes.train.subhalos.threshold_fraction"),
        (
            {"subhalos": {"count": {"dist": "uniform", "low": 0, "high": 5}}},
            "scenes.train.subhalos.count",
        ),
        (
            {"subhalos": {"gamma": {"dist": "uniform", "low": 0.5, "high": 2.9}}},
            "scenes.train.subhalos.gamma",
        ),
        (
            {"subhalos": {"mass": {"slope": -1.9, "m_min": 1e10, "m_max": 1e7}}},
            "scenes.train.subhalos.mass.low",
        ),
        (
            {"redshifts": {"z_source": {"dist": "uniform", "low": 0.2, "high": 0.7}}},
            "scenes.train.redshifts",
        ),
        ({"source": {"split": "dev"}}, "scenes.train.source.split"),
        ({"components": {"shear": "yes"}}, "scenes.train.components.shear"),
        ({"images_per_set": 0}, "scenes.train.images_per_set"),
        ({"los": {"profile": "tnfw"}}, "scenes.train.los.profile"),
        ({"concentration": {"multipliers": []}}, "scenes.train.concentration.multipliers"),
    ],
)
def test_bad_scene_config_names_key(spec, needle):
    with pytest.raises(PriorError) as err:  # SceneError is a PriorError
        scenes_from_config({"train": spec})
    assert needle in str(err.value)
    assert isinstance(err.value, ValueError)


def test_macro_keys_shapes_and_ranges(scenes, rng):
    m = sample_macro(scenes["train"], 500, rng)
    expected = ALWAYS | {
        "a3",
        "phi3",
        "a4",
        "phi4",
        "shear_g1",
        "shear_g2",
        "light_mag",
        "light_r",
        "light_n",
        "light_e1",
        "light_e2",
        "n_sub",
        "gamma_sub",
        "delta_los",
    }
    assert set(m) == expected
    for k, v in m.items():
        assert v.shape == (500,), k
        assert v.dtype == (np.int64 if k in ("n_sub", "set_index") else np.float64), k
    assert np.all((m["theta_e"] >= 0.9) & (m["theta_e"] <= 1.3))
    assert np.all((m["gamma_ml"] >= 1.1) & (m["gamma_ml"] <= 2.9))
    assert np.all((m["n_sub"] >= 0) & (m["n_sub"] <= 3000))
    assert np.all(m["light_r"] > 0) and np.all((m["light_n"] >= 0.5) & (m["light_n"] <= 8))
    assert np.all(m["z_source"] > m["z_lens"])
    assert np.array_equal(m["set_index"], np.arange(500))
    g = sample_macro(scenes["train"], 5000, rng)["gamma_sub"]
    assert stats.kstest(g, stats.uniform(1.1, 1.8).cdf).pvalue > 1e-3


def test_components_off_are_absent_and_other_draws_unchanged(scenes):
    off = Scene.from_config(
        "train",
        {
            "components": {
                "lens_light": False,
                "multipoles": False,
                "shear": False,
                "subhalos": False,
                "los": False,
            }
        },
    )
    a = sample_macro(off, 50, np.random.default_rng(1))
    b = sample_macro(scenes["train"], 50, np.random.default_rng(1))
    # EPL LoS off and subhalos off: no label either.
    assert set(a) == ALWAYS
    for k in ALWAYS:
        assert np.array_equal(a[k], b[k]), k
    only_los = Scene.from_config("train", {"components": {"subhalos": False}})
    c = sample_macro(only_los, 50, np.random.default_rng(1))
    assert "n_sub" not in c and "gamma_sub" in c and "delta_los" in c


def test_sets_share_gamma(scenes, rng):
    m = sample_macro(scenes["test_epl"], 13 * 40, rng)
    g = m["gamma_sub"].reshape(40, 13)
    assert np.all(g == g[:, :1])
    assert np.unique(g[:, 0]).size == 40
    assert np.array_equal(m["set_index"], np.repeat(np.arange(40), 13))
    assert np.unique(m["theta_e"]).size == 13 * 40  # other parameters vary per image
    with pytest.raises(ValueError, match="multiple of images_per_set"):
        sample_macro(scenes["test_epl"], 20, rng)


def test_same_seed_identical_draws(scenes):
    a = sample_macro(scenes["validation"], 64, np.random.default_rng(42))
    b = sample_macro(scenes["validation"], 64, np.random.default_rng(42))
    c = sample_macro(scenes["validation"], 64, np.random.default_rng(43))
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    assert not np.array_equal(a["theta_e"], c["theta_e"])


def test_cdm_scene_multiplier(scenes, rng):
    with pytest.raises(ValueError, match="multiplier"):
        sample_macro(scenes["nfw"], 13, rng)
    m = sample_macro(scenes["nfw"], 26, rng, multiplier=2.0)
    assert "gamma_sub" not in m and np.all(m["c_multiplier"] == 2.0)
    one = Scene.from_config("nfw", {"concentration": {"multipliers": [1.0]}})
    assert np.all(sample_macro(one, 13, rng)["c_multiplier"] == 1.0)


def test_sersic_source_keys(rng):
    s = Scene.from_config("train", {"source": {"kind": "sersic"}})
    m = sample_macro(s, 10, rng)
    assert {"src_mag", "src_r", "src_n", "src_e1", "src_e2"} <= set(m)
    assert "src_mag" not in sample_macro(Scene.from_config("train"), 10, rng)


def test_config_fragment_matches_presets_and_schema():
    cfg = yaml.safe_load(FRAGMENT.read_text(encoding="utf-8"))
    from_fragment = scenes_from_config(cfg["scenes"])
    from test_config import SHIPPED_SCENE_CHOICES as realism
    from test_config import shipped_scenes

    expected = shipped_scenes(PRESETS)
    assert from_fragment == scenes_from_config(expected)
    frag = yaml.safe_load(SCHEMA_FRAGMENT.read_text(encoding="utf-8"))
    schema = {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "type": "object",
        "properties": frag["properties"],
        "$defs": frag["$defs"],
    }
    jsonschema.Draft202012Validator.check_schema(schema)
    validator = jsonschema.Draft202012Validator(schema)
    assert not list(validator.iter_errors(cfg))
    bad = {"scenes": {"train": {"main_lens": {"theta_e": {"dist": "uniform", "low": 1}}}}}
    assert list(validator.iter_errors(bad))
    bad = {"scenes": {"nfw": {"subhalos": {"profile": "burkert"}}}}
    assert list(validator.iter_errors(bad))
    # Every schema default of a scene key equals the train preset value.
    train = yaml.safe_load(FRAGMENT.read_text(encoding="utf-8"))["scenes"]["train"]

    def check(props, values, where):
        for key, entry in props.items():
            if "properties" in entry and values[key] is not None:  # nested (source.multi_sersic)
                check(entry["properties"], values[key], f"{where}.{key}")
            elif "default" in entry and key not in realism.get(where, {}):
                assert entry["default"] == values[key], f"{where}.{key}"

    from subslope.simulation.presets import LENS_LIGHT_PRIORS

    train["lens_light"] = LENS_LIGHT_PRIORS["table1"]  # the schema's defaults: Table 1
    for section, sub in frag["$defs"]["scene"]["properties"].items():
        check(sub.get("properties", {}), train.get(section, {}), section)


# ------------------------------------------------------------------ multi-Sérsic source
MULTI = {"source": {"kind": "multi_sersic"}}


def test_multi_sersic_layout_and_priors(rng):
    from subslope.simulation.scenes import MULTI_SERSIC_KEYS, multi_sersic_keys

    s = Scene.from_config("train", MULTI)
    assert s.source.multi_sersic.max_components == 4
    m = sample_macro(s, 400, rng)
    keys = multi_sersic_keys(4)
    assert set(keys) <= set(m) and len(keys) == 2 + 4 * len(MULTI_SERSIC_KEYS)
    assert "src_mag" not in m and "src_r" not in m  # the single-Sérsic keys are not emitted
    for k in keys:
        assert m[k].shape == (400,) and np.all(np.isfinite(m[k])), k
    assert m["src_ncomp"].dtype == np.int64 and set(np.unique(m["src_ncomp"])) == {1, 2, 3, 4}
    frac = np.stack([m[f"src_frac_{j}"] for j in range(4)])
    np.testing.assert_allclose(frac.sum(0), 1.0, rtol=0, atol=1e-12)
    for j in range(4):  # slots beyond the count carry zero flux, slots within it positive flux
        assert np.all((frac[j] > 0) == (j < m["src_ncomp"]))
    assert np.all(m["src_dx_0"] == 0) and np.all(m["src_dy_0"] == 0)
    off = np.hypot(m["src_dx_1"], m["src_dy_1"])
    assert off.min() >= 0.05 - 1e-12 and off.max() <= 0.35 + 1e-12
    assert m["src_r_1"].min() >= 0.02 and m["src_r_1"].max() <= 0.1
    assert 20 <= m["src_mag_total"].min() and m["src_mag_total"].max() <= 23


def test_multi_sersic_same_seed_and_other_draws_unchanged():
    s = Scene.from_config("train", MULTI)
    a = sample_macro(s, 50, np.random.default_rng(5))
    b = sample_macro(s, 50, np.random.default_rng(5))
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    # the multi-Sérsic draws come last: the other parameters equal the Sérsic-kind draws
    c = sample_macro(
        Scene.from_config("train", {"source": {"kind": "sersic"}}), 50, np.random.default_rng(5)
    )
    for k in ("theta_e", "gamma_ml", "n_sub", "gamma_sub", "lens_x", "delta_los"):
        assert np.array_equal(a[k], c[k]), k
    np.testing.assert_array_equal(a["src_mag_total"], c["src_mag"])
    np.testing.assert_array_equal(a["src_r_0"], c["src_r"])


def test_multi_sersic_fixed_count_and_bad_configs():
    s = Scene.from_config(
        "train", {"source": {"kind": "multi_sersic", "multi_sersic": {"n_components": 1}}}
    )
    m = sample_macro(s, 5, np.random.default_rng(0))
    assert np.all(m["src_ncomp"] == 1) and np.all(m["src_frac_0"] == 1) and "src_frac_1" not in m
    for bad, needle in [
        (
            {"n_components": {"dist": "uniform_int", "low": 0, "high": 3}},
            "multi_sersic.n_components",
        ),
        (
            {"n_components": {"dist": "uniform_int", "low": 1, "high": 9}},
            "multi_sersic.n_components",
        ),
        ({"n_components": {"dist": "uniform", "low": 1, "high": 3}}, "multi_sersic.n_components"),
        ({"r_sersic": {"dist": "uniform", "low": -0.1, "high": 0.1}}, "multi_sersic.r_sersic"),
        ({"share": {"dist": "uniform", "low": -1, "high": 1}}, "multi_sersic.share"),
        ({"clumps": 3}, "multi_sersic.clumps"),
    ]:
        with pytest.raises(SceneError) as err:
            Scene.from_config("train", {"source": {"kind": "multi_sersic", "multi_sersic": bad}})
        assert needle in str(err.value)


def test_schema_accepts_and_rejects_multi_sersic():
    frag = yaml.safe_load(SCHEMA_FRAGMENT.read_text(encoding="utf-8"))
    schema = {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "type": "object",
        "properties": frag["properties"],
        "$defs": frag["$defs"],
    }
    v = jsonschema.Draft202012Validator(schema)

    def ok(src):
        return not list(v.iter_errors({"scenes": {"train": {"source": src}}}))

    assert ok({"kind": "multi_sersic"})
    assert ok(
        {
            "kind": "multi_sersic",
            "multi_sersic": {
                "n_components": 3,
                "offset": {"dist": "uniform", "low": 0, "high": 0.5},
            },
        }
    )
    assert ok(
        {
            "kind": "multi_sersic",
            "multi_sersic": {"n_components": {"dist": "uniform_int", "low": 2, "high": 8}},
        }
    )
    assert not ok({"kind": "multisersic"})
    assert not ok({"kind": "multi_sersic", "multi_sersic": {"n_components": 0}})
    assert not ok(
        {
            "kind": "multi_sersic",
            "multi_sersic": {"n_components": {"dist": "uniform_int", "low": 1, "high": 9}},
        }
    )
    assert not ok(
        {
            "kind": "multi_sersic",
            "multi_sersic": {"n_components": {"dist": "uniform", "low": 1, "high": 3}},
        }
    )
    assert not ok({"kind": "multi_sersic", "multi_sersic": {"clumps": 2}})


def test_named_lens_light_priors():
    from subslope.simulation.presets import LENS_LIGHT_PRIORS

    table1 = Scene.from_config("train")
    fits = Scene.from_config("train", {"lens_light": {"prior": "hst_fits"}})
    assert (
        table1.lens_light
        == Scene.from_config("train", {"lens_light": {"prior": "table1"}}).lens_light
    )
    assert fits.lens_light.mag.support == (13.02, 16.9)
    assert set(LENS_LIGHT_PRIORS) == {"table1", "hst_fits", "hst_joint"}
    # a prior written beside the name overrides that one key
    one = Scene.from_config(
        "nfw",
        {"lens_light": {"prior": "hst_fits", "mag": {"dist": "uniform", "low": 16, "high": 17}}},
    )
    assert (
        one.lens_light.mag.support == (16, 17)
        and one.lens_light.n_sersic == fits.lens_light.n_sersic
    )
    with pytest.raises(
        SceneError,
        match=r"scenes.train.lens_light.prior = 'sdss'; allowed: hst_fits, hst_joint, table1",
    ):
        Scene.from_config("train", {"lens_light": {"prior": "sdss"}})


def test_joint_lens_light_prior_draws_round_lenses_and_replaces_the_boxes(rng):
    from subslope.simulation.presets import LENS_LIGHT_PRIORS

    joint = Scene.from_config("train", {"lens_light": {"prior": "hst_joint"}})
    assert joint.lens_light.joint is not None
    assert Scene.from_config("train").lens_light.joint is None
    m = sample_macro(joint, 20_000, rng)
    e = np.hypot(m["light_e1"], m["light_e2"])
    q = (1 - e) / (1 + e)
    spec = LENS_LIGHT_PRIORS["hst_joint"]["joint"]
    assert np.percentile(q, 99) > 0.93  # J1142+1001 (q = 0.93) is covered
    assert q.min() >= spec["low"]["q"] - 1e-12
    np.testing.assert_allclose(np.median(m["light_mag"]), spec["mean"]["mag"], atol=0.05)
    # brighter lenses are larger: the fits' correlation survives the draw
    assert np.corrcoef(m["light_mag"], np.log(m["light_r"]))[0, 1] < -0.5
    # the position angle is uniform: no preferred e1 or e2 sign
    assert abs(np.mean(m["light_e1"])) < 0.01 and abs(np.mean(m["light_e2"])) < 0.01
    # the joint draw comes after the others: every other parameter is unchanged
    plain = sample_macro(Scene.from_config("train"), 50, np.random.default_rng(9))
    other = sample_macro(joint, 50, np.random.default_rng(9))
    assert all(np.array_equal(plain[k], other[k]) for k in plain if not k.startswith("light_"))


def test_sky_level_is_drawn_last_and_only_when_on():
    spec = {
        "components": {"sky": True},
        "sky": {"level": {"dist": "uniform", "low": 0.05, "high": 0.2}},
    }
    on = sample_macro(Scene.from_config("train", spec), 40, np.random.default_rng(2))
    off = sample_macro(Scene.from_config("train"), 40, np.random.default_rng(2))
    assert "sky_level" not in off
    assert np.all((on["sky_level"] >= 0.05) & (on["sky_level"] <= 0.2))
    assert all(np.array_equal(off[k], on[k]) for k in off)


@pytest.mark.parametrize(
    "joint, needle",
    [
        ({"widen": -1.0}, "lens_light.joint.widen"),
        ({"low": {"mag": 10.0, "ln_r": -3.0, "n": 0.1, "q": 0.2}}, "box of n"),
        ({"mean": {"mag": 16.0, "r": 0.3}}, "lens_light.joint.mean.r"),
    ],
)
def test_bad_joint_lens_light_names_the_key(joint, needle):
    from subslope.simulation.presets import LENS_LIGHT_PRIORS

    spec = {**LENS_LIGHT_PRIORS["hst_joint"]["joint"], **joint}
    with pytest.raises(ValueError, match=needle):  # SceneError or PriorError
        Scene.from_config("train", {"lens_light": {"prior": "hst_joint", "joint": spec}})
