"""Configuration schema and loader: defaults, and one failure per kind of bad value."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from subslope import config as cfg
from subslope.cli import main as cli_main

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "config" / "config.yaml"


def test_shipped_config_is_valid_and_complete():
    loaded = cfg.load(CONFIG, env=False)
    # The shipped file spells out every key, so it equals the pure-defaults config.
    assert loaded == cfg.validate({})
    assert loaded["instrument"]["pixel_scale"] == 0.04
    assert loaded["instrument"]["npix"] == 100
    assert loaded["instrument"]["psf"]["source"] == "empirical"
    assert loaded["cosmology"]["name"] == "Planck18"
    assert loaded["stages"]["gallery"] is True


def test_every_schema_key_is_typed_described_defaulted():
    def walk(schema, path):
        for key, sub in schema.get("properties", {}).items():
            where = f"{path}.{key}".lstrip(".")
            assert "type" in sub and "description" in sub and "default" in sub, where
            if sub["type"] in ("number", "integer") and key != "seed":
                assert {"minimum", "exclusiveMinimum"} & set(sub), f"{where} has no lower bound"
                assert {"maximum", "exclusiveMaximum"} & set(sub), f"{where} has no upper bound"
            if sub["type"] == "object":
                assert sub.get("additionalProperties") is False, where
                walk(sub, where)

    schema = cfg.load_schema()
    assert schema["additionalProperties"] is False
    walk(schema, "")


def test_workflow_schema_is_the_package_schema():
    link = REPO / "workflow" / "schemas" / "config.schema.yaml"
    assert link.resolve() == cfg.schema_path().resolve()


def test_defaults_fill_partial_sections():
    out = cfg.validate({"instrument": {"psf": {"source": "gaussian"}}})
    assert out["instrument"]["psf"] == {
        "source": "gaussian", "file": "psf/emp_psf_f814w.fits", "index": 17,
        "supersampling": 4, "fwhm": 0.1,
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
        ({"instrument": {"psf": {"source": "airy"}}}, "instrument.psf.source", "'empirical', 'gaussian'"),  # enum
        ({"cosmology": {"name": "WMAP9"}}, "cosmology.name", "'Planck18'"),
        ({"run_name": "has space"}, "run_name", "matching"),
        ({"data": {"mirorr": "x"}}, "data.mirorr", "mirror"),  # unknown key
        ({"trainig": {}}, "trainig", "run_name"),
        ({"stages": {"galery": True}}, "stages.galery", "gallery"),
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
