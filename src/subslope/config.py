"""Workflow configuration: loading, default filling and validation.

The schema ``subslope/schemas/config.schema.yaml`` (JSON schema, draft 2020-12, in YAML)
is the single description of every configuration key: its type, meaning, default and,
for physical numbers, its allowed range. The Snakemake workflow validates against the
same file when it loads (``workflow/schemas/config.schema.yaml`` links to it); this
module gives Python the same check with readable errors::

    cfg = subslope.config.load("config/config.yaml")   # defaults filled, validated

A bad value raises :class:`ConfigError` whose message names the key path (``data.mirror``),
the offending value and what is allowed.
"""

from __future__ import annotations

import copy
import os
from collections.abc import Mapping
from importlib import resources as importlib_resources
from pathlib import Path
from typing import Any

import jsonschema
import yaml

__all__ = [
    "ConfigError",
    "MIRROR_ENV_VAR",
    "schema_path",
    "load_schema",
    "fill_defaults",
    "validate",
    "load",
    "apply_env_overrides",
]

#: Environment variable that overrides ``data.mirror``.
MIRROR_ENV_VAR = "SUBSLOPE_DATA_MIRROR"


class ConfigError(ValueError):
    """A configuration value is missing, of the wrong type or outside its allowed range."""


def schema_path() -> Path:
    """Path of the canonical configuration schema shipped inside the package."""
    return Path(str(importlib_resources.files("subslope") / "schemas" / "config.schema.yaml"))


def load_schema() -> dict[str, Any]:
    """The configuration schema as a dictionary."""
    with open(schema_path(), encoding="utf-8") as handle:
        return yaml.safe_load(handle)


def fill_defaults(config: Mapping[str, Any], schema: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Return a deep copy of ``config`` with every missing key set to its schema default.

    Sections (objects) whose default is ``{}`` are created and then filled recursively,
    so an empty config yields the complete default configuration. Values of the wrong
    type are left alone for :func:`validate` to report.
    """
    schema = load_schema() if schema is None else schema
    out = copy.deepcopy(dict(config))
    _fill(out, schema)
    return out


def _fill(instance: dict[str, Any], schema: Mapping[str, Any]) -> None:
    for key, sub in schema.get("properties", {}).items():
        if key not in instance and "default" in sub:
            instance[key] = copy.deepcopy(sub["default"])
        if isinstance(instance.get(key), dict) and "properties" in sub:
            _fill(instance[key], sub)


def _key_path(parts) -> str:
    return ".".join(str(p) for p in parts) or "<top level>"


def _allowed(schema: Mapping[str, Any]) -> str:
    """Human-readable description of what a (sub)schema allows."""
    bits: list[str] = []
    if "enum" in schema:
        bits.append("one of " + ", ".join(repr(v) for v in schema["enum"]))
    else:
        types = schema.get("type")
        if types is not None:
            types = [types] if isinstance(types, str) else list(types)
            bits.append(" or ".join(types))
    lo = schema.get("minimum", schema.get("exclusiveMinimum"))
    hi = schema.get("maximum", schema.get("exclusiveMaximum"))
    if lo is not None or hi is not None:
        left = "(" if "exclusiveMinimum" in schema else "["
        right = ")" if "exclusiveMaximum" in schema else "]"
        lo_s = "-inf" if lo is None else repr(lo)
        hi_s = "inf" if hi is None else repr(hi)
        bits.append(f"in {left}{lo_s}, {hi_s}{right}")
    if "pattern" in schema:
        bits.append(f"matching {schema['pattern']!r}")
    if "minLength" in schema:
        bits.append(f"at least {schema['minLength']} character(s)")
    if "maxLength" in schema:
        bits.append(f"at most {schema['maxLength']} characters")
    return ", ".join(bits) if bits else "see the schema"


def _describe(error: jsonschema.ValidationError) -> str:
    path = list(error.absolute_path)
    if error.validator == "additionalProperties":
        known = set(error.schema.get("properties", {}))
        unknown = sorted(k for k in error.instance if k not in known)
        keys = ", ".join(_key_path(path + [k]) for k in unknown)
        return (
            f"unknown config key(s) {keys}; allowed keys at {_key_path(path)}: "
            + ", ".join(sorted(known))
        )
    if error.validator == "required":
        return f"config key {_key_path(path)}: {error.message}"
    # The failing keyword sits in error.schema; the bounds/types of the whole key are in
    # the parent schema of that keyword, which for our flat schema is error.schema itself.
    return (
        f"config key {_key_path(path)} = {error.instance!r} is not allowed "
        f"(failed '{error.validator}'); allowed: {_allowed(error.schema)}"
    )


def validate(config: Mapping[str, Any], *, fill: bool = True) -> dict[str, Any]:
    """Validate ``config`` against the schema and return it with defaults filled.

    Raises :class:`ConfigError` listing every problem, one per line, each naming its key.
    """
    if not isinstance(config, Mapping):
        raise ConfigError(f"the configuration must be a mapping of keys, got {type(config).__name__}")
    schema = load_schema()
    full = fill_defaults(config, schema) if fill else copy.deepcopy(dict(config))
    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(full), key=lambda e: [str(p) for p in e.absolute_path])
    if errors:
        lines = "\n".join("  - " + _describe(e) for e in errors)
        raise ConfigError(f"invalid configuration ({len(errors)} problem(s)):\n{lines}")
    return full


def apply_env_overrides(config: dict[str, Any]) -> dict[str, Any]:
    """Apply environment overrides in place (``SUBSLOPE_DATA_MIRROR`` → ``data.mirror``)."""
    value = os.environ.get(MIRROR_ENV_VAR)
    if value:
        config.setdefault("data", {})["mirror"] = value
    return config


def load(path: str | os.PathLike[str], *, env: bool = True) -> dict[str, Any]:
    """Read a YAML config file, fill defaults, validate, and apply environment overrides.

    Parameters
    ----------
    path:
        YAML file (an empty file means "all defaults").
    env:
        Apply :func:`apply_env_overrides` after validation (default True).
    """
    path = Path(path)
    try:
        with open(path, encoding="utf-8") as handle:
            raw = yaml.safe_load(handle)
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {path}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {path} is not valid YAML: {exc}") from None
    raw = {} if raw is None else raw
    try:
        config = validate(raw)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    return apply_env_overrides(config) if env else config
