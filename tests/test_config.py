"""Configuration schema and loader: defaults, and one failure per kind of bad value."""

from __future__ import annotations

import copy
import os
import re
import shutil
from pathlib import Path

import pytest
import yaml

from subslope import config as cfg
from subslope.cli import main as cli_main
from subslope.simulation.presets import OPTIONAL_KEYS
from subslope.simulation.scenes import PRESETS, scenes_from_config
from tests.conftest import REPO_ROOT

REPO_CONFIG = REPO_ROOT / "config" / "config.yaml"

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "config" / "config.yaml"


#: Keys of config/config.yaml that deliberately differ from the schema defaults (the
#: reference values): the 10 bundled COSMOS galaxies need relaxed cuts and a coarser split;
#: the reduced campaign's sizes, compiled rendering and training settings for a 2-core CPU.
SHIPPED_DEVIATIONS = {
    ("simulation", "sources", "folder"),
    ("simulation", "sources", "clean"),
    ("simulation", "sources", "cuts"),
    ("simulation", "sources", "split"),
    ("simulation", "sources", "mag_renormalize"),
    ("simulation", "scenes"),
    ("simulation", "multipliers"),
    ("simulation", "render", "compile"),
    ("instrument", "noise_correlation"),
    ("training", "batch_size"),
    ("training", "num_workers"),
    ("training", "checkpoint_every"),
    ("training", "min_delta"),
    ("training", "max_epochs"),
    ("training", "inputs"),
    ("training", "augment"),
    ("null_tests", "scenes"),
    ("cdm", "reference_nfw_scene"),
    ("cdm", "reference_tnfw_scene"),
    ("cdm", "field_controls"),
    ("cdm", "reference_controls"),
    ("cdm", "extra_scenes"),
    ("cdm", "abundance"),
    ("systematics", "variants"),
    ("systematics", "common"),
}

#: The null-test scenes of config/config.yaml: the test sets without subhalos.
NULL_SCENES = {
    "null_nosub": {"subhalos": {"count": 0}, "components": {"los": False, "sky": True}},
    "null_nosub_los": {"subhalos": {"count": 0}, "los": {"profile": "nfw"}},
}

#: Scene keys without a schema default (their preset differs between scenes; see the
#: header of the schema): paths relative to $defs.scene.
SCENE_KEYS_WITHOUT_DEFAULT = {
    "images_per_set",
    "source.split",
    "subhalos.count",
    "subhalos.profile",
    "subhalos.placement",
    "los.profile",
    # optional keys: absent means off, no preset holds them (simulation.presets.OPTIONAL_KEYS)
    "common_draws",
    "subhalos.fixed_gamma",
}

#: Keys outside the scenes whose absence means something, so they carry no default:
#: a simulated scene's own multipliers (absent: simulation.multipliers).
KEYS_WITHOUT_DEFAULT = ("simulation.scenes.<scene>.multipliers",)


#: Where every scene of config/config.yaml departs from the paper's presets: the choices
#: that make the simulations cover the HST lenses (docs/simulation.md).
SHIPPED_SCENE_CHOICES = {
    "lens_light": {"prior": "hst_joint"},
    "components": {"sky": True},
    "sky": {"level": {"dist": "normal", "mean": 0.0661, "std": 0.0813, "low": 0.0}},
    "main_lens": {
        "x": {"dist": "uniform", "low": -0.3, "high": 0.3},
        "y": {"dist": "uniform", "low": -0.3, "high": 0.3},
        "theta_e": {"dist": "uniform", "low": 0.9, "high": 1.5},
    },
}

#: The reference code's CDM sets (cdm.reference_*_scene): as nfw and tnfw, with
#: N_sub ~ U{0, 12000} where the source stamp lands and the subhalos' sheet at the origin.
REFERENCE_SUBHALOS = {
    "count": {"dist": "uniform_int", "low": 0, "high": 12000},
    "placement": "landing",
    "threshold_fraction": 0.01,
    "sheet_centre": "origin",
}


def shipped_scenes(scene_names) -> dict:
    """What config/config.yaml declares for each scene, spelled from the presets and the
    choices above: the realism choices everywhere, the test-set keys, the null scenes, the
    reference code's CDM sets with its centroid variant and the abundance series, and
    the matched EPL controls of both grids."""
    out = {name: SHIPPED_SCENE_CHOICES for name in scene_names}
    test_sets = {"images_per_set": 13, "source": {"split": "test"}, **SHIPPED_SCENE_CHOICES}
    out.update({name: {**test_sets, **spec} for name, spec in NULL_SCENES.items()})

    def reference(profile, **subhalos):
        sub = {**REFERENCE_SUBHALOS, "profile": profile, **subhalos}
        return {**test_sets, "subhalos": sub, "los": {"profile": "nfw"}}

    out["nfw_ref"], out["tnfw_ref"] = reference("nfw"), reference("tnfw")
    out["nfw_ref_centroid"] = reference("nfw", sheet_centre="mass_centroid")
    for n_max in (400, 1800, 3000, 6000):
        count = {"dist": "uniform_int", "low": 0, "high": n_max}
        out[f"nfw_ref_n{n_max}"] = reference("nfw", count=count)
        out[f"tnfw_ref_n{n_max}"] = reference("tnfw", count=count)
    field = {"count": {"dist": "uniform_int", "low": 0, "high": 1800}, "placement": "everywhere"}
    for gamma in (1.5, 1.8, 2.1, 2.4):
        tag = f"{round(10 * gamma)}"
        out[f"epl_control_{tag}"] = {
            **test_sets,
            "common_draws": True,
            "subhalos": {**field, "fixed_gamma": gamma},
            "los": {"profile": "nfw"},
        }
        out[f"epl_control_ref_{tag}"] = {
            **reference("epl", fixed_gamma=gamma),
            "common_draws": True,
        }
    return out


def _without(config, paths):
    out = copy.deepcopy(config)
    for path in paths:
        node = out
        for key in path[:-1]:
            node = node[key]
        node.pop(path[-1])
    return out


def test_shipped_config_is_valid_and_complete():
    loaded = cfg.load(CONFIG, env=False)
    defaults = cfg.validate({})
    # The shipped file spells out every key, so apart from the documented deviations
    # it equals the pure-defaults config; scenes compare as resolved Scene objects
    # (the file writes the train scene out in full, the defaults are the presets).
    chosen = shipped_scenes(defaults["scenes"] or PRESETS)
    assert scenes_from_config(loaded["scenes"]) == scenes_from_config(chosen)
    assert loaded["null_tests"]["scenes"] == list(NULL_SCENES)
    strip = SHIPPED_DEVIATIONS | {("scenes",)}
    assert _without(loaded, strip) == _without(defaults, strip)
    assert loaded["simulation"]["sources"]["cuts"]["mag_max"] is None
    assert loaded["instrument"]["pixel_scale"] == 0.04
    assert loaded["instrument"]["npix"] == 100
    assert loaded["instrument"]["noise_correlation"] == [0.32, 0.55]  # docs/realism.md
    assert loaded["instrument"]["psf"]["source"] == "empirical"
    assert loaded["cosmology"]["name"] == "Planck18"
    assert loaded["stages"]["gallery"] is True
    assert loaded["stages"]["simulate"] is True
    assert loaded["training"]["seed"] is None and loaded["calibration"]["seed"] is None


def test_tiny_config_is_valid():
    tiny = cfg.load(REPO / "config" / "tiny.yaml", env=False)
    counts = tiny["simulation"]["scenes"]
    scenes = scenes_from_config(tiny["scenes"])
    for name, c in counts.items():
        assert c["images_per_shard"] % scenes[name].images_per_set == 0, name
        assert c["n_shards"] * c["images_per_shard"] <= 16, name
    assert tiny["training"]["max_epochs"] <= 2 and tiny["inference"]["gamma_grid"]["n"] <= 32
    assert all(tiny["stages"].values())  # the tiny run exercises the whole DAG
    per_set = scenes[tiny["calibration"]["stack_scene"]].images_per_set
    assert max(tiny["calibration"]["n_images"]) <= per_set
    assert len(tiny["hst"]["combine"]) in tiny["calibration"]["n_images"]


def test_shipped_campaign_sections():
    loaded = cfg.load(CONFIG, env=False)
    assert 1.0 in loaded["simulation"]["multipliers"]
    assert loaded["calibration"]["n_images"] == [1, 2, 3, 5, 8, 13]
    assert loaded["calibration"]["level"] == 0.68
    assert "SDSSJ0946+1006" in loaded["hst"]["show"] and loaded["hst"]["combine"] is None
    assert all(loaded["stages"].values())
    scenes = scenes_from_config(loaded["scenes"])
    for name, c in loaded["simulation"]["scenes"].items():
        assert c["images_per_shard"] % scenes[name].images_per_set == 0, name
    assert max(loaded["calibration"]["n_images"]) <= scenes["test_epl"].images_per_set


def test_every_schema_key_is_typed_described_defaulted():
    schema = cfg.load_schema()
    defs = schema["$defs"]
    seen_refs: set[str] = set()
    without_default: set[str] = set()

    def resolve(sub):
        ref = sub.get("$ref")
        if ref is None:
            return sub, None
        assert ref.startswith("#/$defs/"), ref
        name = ref.split("/")[-1]
        return {**defs[name], **{k: v for k, v in sub.items() if k != "$ref"}}, name

    def check_prior(where):
        for branch in defs["prior"]["oneOf"]:
            assert "type" in branch, f"{where}: prior branch without type"
            if branch["type"] == "object":
                assert branch.get("additionalProperties") is False, where
                for key, field in branch["properties"].items():
                    assert "description" in field, f"{where}.{key}"

    def walk(schema, path, scene_path=None):
        entries = dict(schema.get("properties", {}))
        if isinstance(schema.get("additionalProperties"), dict):
            entries["<any>"] = schema["additionalProperties"]
        for key, raw in entries.items():
            where = f"{path}.{key}".lstrip(".")
            sub, ref = resolve(raw)
            inner = None if scene_path is None else f"{scene_path}.{key}".lstrip(".")
            assert "description" in sub or key == "<any>", where
            if "default" not in sub and key != "<any>":
                generic = re.sub(
                    r"^simulation\.scenes\.[^.]+\.", "simulation.scenes.<scene>.", where
                )
                assert inner is not None or generic in KEYS_WITHOUT_DEFAULT, (
                    f"{where} has no default"
                )
                if inner is not None:
                    without_default.add(inner)
            if ref == "prior":
                check_prior(where)
                continue
            assert "type" in sub, where
            types = {sub["type"]} if isinstance(sub["type"], str) else set(sub["type"])
            if types & {"number", "integer"} and key != "seed":
                assert {"minimum", "exclusiveMinimum"} & set(sub), f"{where} has no lower bound"
                assert {"maximum", "exclusiveMaximum"} & set(sub), f"{where} has no upper bound"
            if "object" in types and "properties" in sub:
                if ref is not None:
                    if ref in seen_refs:
                        continue
                    seen_refs.add(ref)
                is_scene = ref == "scene"
                assert sub.get("additionalProperties") is False or (
                    "propertyNames" in sub and isinstance(sub.get("additionalProperties"), dict)
                ), where
                walk(sub, where, "" if is_scene else (inner if scene_path is not None else None))

    assert schema["additionalProperties"] is False
    walk(schema, "")
    assert {"scene", "prior", "shard_counts"} <= seen_refs | {"prior"}
    assert without_default == SCENE_KEYS_WITHOUT_DEFAULT
    assert {".".join(k) for k in OPTIONAL_KEYS} <= SCENE_KEYS_WITHOUT_DEFAULT


def test_workflow_schema_is_the_package_schema():
    link = REPO / "workflow" / "schemas" / "config.schema.yaml"
    assert link.resolve() == cfg.schema_path().resolve()


def test_defaults_fill_partial_sections():
    out = cfg.validate({"instrument": {"psf": {"source": "gaussian"}}})
    assert out["instrument"]["psf"] == {
        "source": "gaussian",
        "file": "psf/emp_psf_f814w.fits",
        "index": 17,
        "supersampling": 4,
        "fwhm": 0.1,
    }
    assert out["instrument"]["exposure_time"] == 2200
    assert out["data"]["mirror"] == "../shared/data"


@pytest.mark.parametrize(
    "bad, key, allowed",
    [
        ({"seed": "abc"}, "seed", "integer"),  # wrong type
        ({"seed": 1.5}, "seed", "integer"),
        ({"data": {"allow_download": "yes"}}, "data.allow_download", "boolean"),
        ({"instrument": {"pixel_scale": 0.0}}, "instrument.pixel_scale", "(0, 1.0]"),  # bounds
        ({"instrument": {"npix": 4}}, "instrument.npix", "[8, 1024]"),
        ({"instrument": {"read_noise": -1}}, "instrument.read_noise", "[0, 100]"),
        ({"instrument": {"psf": {"index": 56}}}, "instrument.psf.index", "[0, 55]"),
        ({"instrument": {"noise_correlation": 0.8}}, "instrument.noise_correlation", "[0, 0.7071)"),
        (
            {"instrument": {"noise_correlation": [0.3]}},
            "instrument.noise_correlation",
            "number or array",
        ),
        (
            {"instrument": {"psf": {"source": "airy"}}},
            "instrument.psf.source",
            "'empirical', 'gaussian'",
        ),  # enum
        ({"cosmology": {"name": "WMAP9"}}, "cosmology.name", "'Planck18'"),
        ({"run_name": "has space"}, "run_name", "matching"),
        ({"data": {"mirorr": "x"}}, "data.mirorr", "mirror"),  # unknown key
        ({"trainig": {}}, "trainig", "run_name"),
        ({"stages": {"galery": True}}, "stages.galery", "gallery"),
        (
            {"simulation": {"render": {"dtype": "float16"}}},
            "simulation.render.dtype",
            "'float32', 'float64'",
        ),
        (
            {"simulation": {"render": {"batch_images": 0}}},
            "simulation.render.batch_images",
            "[1, 4096]",
        ),
        (
            {"simulation": {"scenes": {"train": {"n_shards": -1, "images_per_shard": 4}}}},
            "simulation.scenes.train.n_shards",
            "[0, 100000]",
        ),
        (
            {"simulation": {"scenes": {"train": {"n_shards": 1}}}},
            "simulation.scenes.train",
            "images_per_shard",
        ),
        ({"simulation": {"multipliers": [0.0]}}, "simulation.multipliers.0", "(0, 1000]"),
        (
            {"simulation": {"sources": {"split": {"train": 1.5}}}},
            "simulation.sources.split.train",
            "[0, 1]",
        ),
        (
            {"simulation": {"sources": {"cuts": {"mag_max": 50}}}},
            "simulation.sources.cuts.mag_max",
            "[10, 30]",
        ),
        (
            {"scenes": {"train": {"subhalos": {"profile": "sis"}}}},
            "scenes.train.subhalos.profile",
            "'epl', 'nfw', 'tnfw'",
        ),
        ({"scenes": {"nfw": {"images_per_set": 0}}}, "scenes.nfw.images_per_set", "[1, 1000]"),
        (
            {"scenes": {"train": {"main_lens": {"theta_ee": 1.0}}}},
            "scenes.train.main_lens.theta_ee",
            "theta_e",
        ),
        ({"stages": {"simulate": "yes"}}, "stages.simulate", "boolean"),
        ({"training": {"batch_size": 1}}, "training.batch_size", "[2, 100000]"),
        (
            {"training": {"arch": {"preset": "vgg"}}},
            "training.arch.preset",
            "'reduced', 'resnet50'",
        ),
        ({"training": {"lr": 0.0}}, "training.lr", "(0, 1]"),
        ({"training": {"optimiser": "sgd"}}, "training.optimiser", "max_epochs"),
        ({"inference": {"gamma_grid": {"n": 2}}}, "inference.gamma_grid.n", "[3, 100000]"),
        ({"inference": {"device": "tpu"}}, "inference.device", "'auto', 'cpu', 'cuda'"),
        ({"calibration": {"level": 1.0}}, "calibration.level", "(0, 1)"),
        ({"calibration": {"n_images": [0]}}, "calibration.n_images.0", "[1, 1000]"),
        ({"hst": {"lens_centre": {"method": "fit"}}}, "hst.lens_centre.method", "'light_centroid'"),
        ({"cdm": {"band": [16, 184]}}, "cdm.band.1", "[0, 100]"),
        ({"stages": {"train": 1}}, "stages.train", "boolean"),
        (
            {"scenes": {"train": {"sky": {"level": {"dist": "normal", "mean": 0.1, "std": -1}}}}},
            "scenes.train.sky.level.std = -1",
            "(0, inf) (a normal prior takes dist, high, low, mean, std)",
        ),
        (
            {"scenes": {"train": {"sky": {"level": {"dist": "gauss", "mean": 1}}}}},
            "scenes.train.sky.level.dist = 'gauss' is not a prior",
            "'uniform', 'normal', 'uniform_int', 'power_law', 'fixed'",
        ),
        (
            {"scenes": {"train": {"sky": {"level": {"dist": "uniform", "low": 0}}}}},
            "scenes.train.sky.level: 'high' is a required property",
            "a uniform prior takes dist, high, low",
        ),
    ],
)
def test_bad_values_name_the_key_and_what_is_allowed(bad, key, allowed):
    with pytest.raises(cfg.ConfigError) as info:
        cfg.validate(bad)
    msg = str(info.value)
    assert key in msg and allowed in msg, msg


def test_all_problems_reported_at_once():
    with pytest.raises(cfg.ConfigError, match=r"2 problem") as info:
        cfg.validate({"seed": -1, "instrument": {"ccd_gain": 0}})
    assert "seed" in str(info.value) and "instrument.ccd_gain" in str(info.value)


def test_load_reports_file_and_yaml_errors(tmp_path):
    with pytest.raises(cfg.ConfigError, match="not found"):
        cfg.load(tmp_path / "nope.yaml")
    broken = tmp_path / "broken.yaml"
    broken.write_text("seed: [1,\n")
    with pytest.raises(cfg.ConfigError, match="not valid YAML"):
        cfg.load(broken)
    bad = tmp_path / "bad.yaml"
    bad.write_text("instrument:\n  exposure_time: -5\n")
    with pytest.raises(cfg.ConfigError, match=r"(?s)bad\.yaml.*instrument\.exposure_time"):
        cfg.load(bad)
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    assert cfg.load(empty, env=False) == cfg.validate({})
    assert isinstance(cfg.ConfigError("x"), ValueError)


def test_env_var_overrides_mirror(tmp_path, monkeypatch):
    monkeypatch.setenv(cfg.MIRROR_ENV_VAR, str(tmp_path))
    assert cfg.load(CONFIG)["data"]["mirror"] == str(tmp_path)
    assert cfg.load(CONFIG, env=False)["data"]["mirror"] == "../shared/data"


def test_cli_validate_config(tmp_path, capsys):
    assert cli_main(["validate-config", str(CONFIG)]) == 0
    printed = yaml.safe_load(capsys.readouterr().out)
    assert printed["run_name"] == "reduced"
    bad = tmp_path / "bad.yaml"
    bad.write_text("instrument:\n  psf:\n    fwhm: 5\n")
    assert cli_main(["validate-config", str(bad)]) == 1
    assert "instrument.psf.fwhm" in capsys.readouterr().err


@pytest.mark.parametrize(
    "overlay, key, allowed",
    [
        (
            {"inference": {"gamma_grid": {"low": 2.5, "high": 1.5}}},
            "inference.gamma_grid.low/high",
            "low < high",
        ),
        (
            {"calibration": {"single_scene": "nonexistent"}},
            "calibration.single_scene",
            "simulated scenes",
        ),
        (
            {"calibration": {"stack_scene": "nowhere"}},
            "calibration.stack_scene",
            "simulated scenes",
        ),
        ({"calibration": {"n_images": [1, 2, 20]}}, "calibration.n_images", "images_per_set = 13"),
        ({"cdm": {"nfw_scene": "missing"}}, "cdm.nfw_scene", "no shards of that scene"),
        ({"simulation": {"multipliers": [0.5, 2.0]}}, "simulation.multipliers", "must include 1.0"),
        (
            {"simulation": {"scenes": {"test_epl": {"n_shards": 1, "images_per_shard": 14}}}},
            "simulation.scenes.test_epl.images_per_shard",
            "multiple",
        ),
    ],
)
def test_cross_key_problems_name_the_key(overlay, key, allowed):
    """The checks that involve several keys live in config.validate, so the CLI and the
    workflow refuse the same configs with the same message."""
    raw = yaml.safe_load(CONFIG.read_text(encoding="utf-8"))
    for section, values in overlay.items():
        if isinstance(raw.get(section), dict) and section != "simulation":
            raw[section] = {**raw[section], **values}
        else:
            merged = copy.deepcopy(raw.get(section, {}))
            for k, v in values.items():
                merged[k] = (
                    {**merged.get(k, {}), **v} if isinstance(v, dict) and k == "scenes" else v
                )
            raw[section] = merged
    with pytest.raises(cfg.ConfigError) as info:
        cfg.validate(raw)
    assert key in str(info.value) and allowed in str(info.value)


def test_cross_key_checks_skip_stages_that_do_not_run():
    raw = yaml.safe_load(CONFIG.read_text(encoding="utf-8"))
    raw["calibration"] = {**raw["calibration"], "single_scene": "nonexistent"}
    raw["stages"] = {**raw["stages"], "calibrate": False}
    assert cfg.validate(raw)["calibration"]["single_scene"] == "nonexistent"


def test_cli_validate_config_runs_the_cross_key_checks(tmp_path, capsys):
    bad = tmp_path / "grid.yaml"
    bad.write_text("inference:\n  gamma_grid: {low: 2.5, high: 1.5, n: 19}\n")
    assert cli_main(["validate-config", str(bad)]) == 1
    assert "inference.gamma_grid" in capsys.readouterr().err


def test_active_stages_follow_the_needs():
    full = cfg.validate({"stages": {"evaluate": False}})
    on = cfg.active_stages(full)
    assert not on["evaluate"] and not on["calibrate"] and not on["cdm_grid"] and not on["hst"]
    assert on["train"] and on["figures"] and on["summary"] and on["gallery"]


@pytest.mark.parametrize(
    ("override", "match"),
    [
        (
            {"scenes": {"train": {"main_lens": {"gamma": {"dist": "fixed", "value": 3.0}}}}},
            r"scenes.train.main_lens.gamma: support \[3.0, 3.0\] .* within \(1.0, 3.0\)",
        ),
        (
            {
                "scenes": {
                    "nfw": {"main_lens": {"gamma": {"dist": "uniform", "low": 1.0, "high": 2}}}
                }
            },
            r"scenes.nfw.main_lens.gamma",
        ),
        (
            {"simulation": {"sources": {"split": {"train": 0.8, "validation": 0.1, "test": 0.05}}}},
            r"simulation.sources.split.train/validation/test = 0.8/0.1/0.05 must sum to 1",
        ),
        (
            {"simulation": {"sources": {"folder": ["cosmos", "nowhere"]}}},
            r"simulation.sources.folder: \['nowhere'\] neither a registered data folder",
        ),
        ({"hst": {"combine": ["SDSSJ0000+0000"]}}, r"hst.combine: unknown system\(s\)"),
        ({"hst": {"highlight": ["J0946"]}}, r"hst.highlight: unknown system\(s\) \['J0946'\]"),
        (
            {"scenes": {"train": {"sky": {"level": {"dist": "uniform", "low": 1, "high": 0}}}}},
            r"scenes.train.sky.level.low = 1.0 must be < scenes.train.sky.level.high = 0.0",
        ),
        (
            {"instrument": {"noise_correlation": [0.5, 0.3]}},
            r"instrument.noise_correlation = \[0.5, 0.3\]: a range \[low, high\] needs low <= high",
        ),
    ],
)
def test_plan_problems_seen_before_any_job(tmp_path, data_dir, override, match):
    """What only the scenes, the registry and the HST catalogue show is refused by
    `subslope validate-config` (and by the workflow when it loads), naming the key."""
    from subslope.cli import main
    from subslope.plan import plan_problems

    base = cfg.validate({"data": {"mirror": str(data_dir), "resources_dir": str(tmp_path)}})

    def merge(a, b):
        for k, v in b.items():
            a[k] = merge(dict(a.get(k) or {}), v) if isinstance(v, dict) else v
        return a

    config = cfg.validate(merge(copy.deepcopy(base), override))
    problems = plan_problems(config)
    assert any(re.search(match, p) for p in problems), problems
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(config))
    assert main(["validate-config", "-q", str(path)]) == 1
    assert not plan_problems(base)


def test_a_prior_over_a_base_replaces_the_old_prior_whole(tmp_path):
    """A layered file's prior is the prior it states: no bound of the base's survives."""
    (tmp_path / "top.yaml").write_text(
        f"base: {REPO_CONFIG}\n"
        "scenes:\n"
        "  train:\n"
        "    main_lens:\n"
        "      theta_e: {dist: normal, mean: 1.1, std: 0.3}\n"
    )
    base = cfg.load(REPO_CONFIG, env=False)["scenes"]["train"]["main_lens"]["theta_e"]
    assert isinstance(base, dict) and "low" in base  # the base bounds it
    top = cfg.load(tmp_path / "top.yaml", env=False)["scenes"]["train"]["main_lens"]["theta_e"]
    assert top == {"dist": "normal", "mean": 1.1, "std": 0.3}
    # a mapping without `dist` still merges key by key
    merged = cfg.deep_merge({"a": {"x": 1, "y": 2}}, {"a": {"y": 3}})
    assert merged == {"a": {"x": 1, "y": 3}}
    assert cfg.deep_merge(
        {"p": {"dist": "uniform", "low": 0, "high": 1}}, {"p": {"dist": "fixed", "value": 2}}
    ) == {"p": {"dist": "fixed", "value": 2}}


def test_a_psf_file_that_is_no_psf_library_is_refused_naming_key_and_file(tmp_path, data_dir):
    from subslope.plan import plan_problems, plan_warnings

    (tmp_path / "psf").mkdir()
    (tmp_path / "psf" / "text.fits").write_text("root:x:0:0:root:/root:/bin/bash\n")
    config = cfg.validate(
        {
            "data": {"mirror": str(data_dir), "resources_dir": str(tmp_path)},
            "instrument": {"psf": {"file": "psf/text.fits"}},
        }
    )
    (problem,) = [p for p in plan_problems(config) if "instrument.psf.file" in p]
    assert "'psf/text.fits'" in problem and str(tmp_path / "psf" / "text.fits") in problem
    assert "is not a PSF library" in problem
    real = data_dir / "psf" / "emp_psf_f814w.fits"
    if real.is_file():  # the real library, but a PSF it does not hold
        shutil.copyfile(real, tmp_path / "psf" / "real.fits")
        good = cfg.validate(
            {
                **config,
                "instrument": {
                    **config["instrument"],
                    "psf": {**config["instrument"]["psf"], "file": "psf/real.fits"},
                },
            }
        )
        assert not [p for p in plan_problems(good) if "instrument.psf.file" in p]
    # a resources folder outside the project is allowed, with a warning that says so
    (warning,) = [w for w in plan_warnings(config, root=REPO_ROOT) if "resources_dir" in w]
    assert "outside the project folder" in warning and "results" in warning


def test_path_keys_outside_the_project_are_said_alike_by_the_workflow_and_validate_config(
    tmp_path, data_dir, capsys
):
    """Every key a run writes under is said when it leaves the project, with what the run
    writes there; validate-config resolves paths against the project folder wherever it
    runs; a COSMOS folder may not leave the resources folder."""
    from subslope.plan import OUTSIDE_KEYS, plan_problems, plan_warnings

    config = cfg.validate(
        {
            "data": {"mirror": str(data_dir), "resources_dir": str(tmp_path / "res")},
            "simulation": {"shard_cache": "/tmp/elsewhere/cache"},
        }
    )
    warnings = " ".join(plan_warnings(config, root=REPO_ROOT))
    assert "data.resources_dir" in warnings and "fetches the reference data" in warnings
    assert "simulation.shard_cache" in warnings and "a copy of every shard" in warnings
    assert set(OUTSIDE_KEYS) >= {"data.resources_dir", "simulation.shard_cache"}
    bad = cfg.validate({"simulation": {"sources": {"folder": "../../../../etc"}}})
    (problem,) = [p for p in plan_problems(bad) if "simulation.sources.folder" in p]
    assert "'../../../../etc'" in problem and "inside data.resources_dir" in problem
    overlay = tmp_path / "outside.yaml"
    overlay.write_text(
        f"base: {REPO_ROOT / 'config' / 'tiny.yaml'}\nsimulation: {{shard_cache: /tmp/x}}\n"
    )
    inside = REPO_ROOT / "config" / "tiny.yaml"
    here = os.getcwd()
    try:
        os.chdir(tmp_path)  # not the project folder: the answer must not change
        assert cli_main(["validate-config", str(inside), "--quiet"]) == 0
        assert "warning" not in capsys.readouterr().err
        assert cli_main(["validate-config", str(overlay), "--quiet"]) == 0
    finally:
        os.chdir(here)
    err = capsys.readouterr().err
    assert "warning: config key simulation.shard_cache = '/tmp/x' lies outside" in err


def test_cost_of_a_campaign_follows_its_config():
    from subslope.campaigns.cost import campaign_cost, scene_cost_factor
    from subslope.plan import shard_jobs

    paper = cfg.load(REPO_ROOT / "config" / "paper.yaml", env=False)
    cost = campaign_cost(
        paper, seconds_per_image=0.05, bytes_per_image=40_000, gpu_images_per_s=500
    )
    assert cost.training_images == 5_000_000 and cost.images > cost.training_images
    assert cost.cpu_hours_simulation == pytest.approx(sum(cost.cpu_hours_by_scene.values()))
    jobs = shard_jobs(paper)
    for name, hours in cost.cpu_hours_by_scene.items():
        images = sum(paper["simulation"]["scenes"][name]["images_per_shard"] for j in jobs
                     if j["scene"] == name)  # fmt: skip
        assert hours == pytest.approx(images * 0.05 * scene_cost_factor(paper, name) / 3600)
    # priced by N_sub and profile: a training-like scene at the training cost, more
    # subhalos dearer, tNFW dearer than NFW at equal N_sub, no subhalos cheapest
    assert scene_cost_factor(paper, "train") == pytest.approx(1.0)
    factors = {n: scene_cost_factor(paper, n) for n in ("nfw", "nfw_ref", "tnfw_ref", "null_nosub")}
    assert factors["null_nosub"] < 1.0 < factors["nfw_ref"] < factors["tnfw_ref"]
    assert factors["nfw"] < factors["nfw_ref"]
    assert cost.disk_gb_shards == pytest.approx(cost.images * 40_000 / 1e9)
    assert cost.gpu_hours_training == pytest.approx(5e6 * cost.max_epochs / 500 / 3600)
    reduced = campaign_cost(cfg.load(REPO_CONFIG, env=False))
    assert reduced.images < cost.images and reduced.shard_jobs < cost.shard_jobs


def test_cli_cost_prints_every_line(capsys):
    from subslope.cli import main

    assert main(["cost", "--config", str(REPO_ROOT / "config" / "paper.yaml")]) == 0
    out = capsys.readouterr().out
    for line in (
        "shard jobs",
        "CPU-hours, simulation",
        "disk of the shards",
        "GPU-hours, training",
    ):
        assert line in out


def test_a_config_is_validated_once_per_process(monkeypatch):
    """Validating a config, then its validated result, then that again runs the
    cross-key checks (the last step of a full validation) once; a changed config is
    validated anew."""
    calls = []
    real = cfg.cross_key_problems
    monkeypatch.setattr(cfg, "cross_key_problems", lambda c: calls.append(1) or real(c))
    raw = cfg.load(REPO_ROOT / "config" / "tiny.yaml", env=False)
    raw["seed"] = 987_654_321  # a config no other test validated in this process
    once = cfg.validate(raw)
    assert cfg.validate(cfg.validate(once)) == once and len(calls) == 1
    changed = copy.deepcopy(raw)
    changed["seed"] += 1
    assert cfg.validate(changed)["seed"] == changed["seed"] and len(calls) == 2
