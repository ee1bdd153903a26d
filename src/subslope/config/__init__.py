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
import functools
import hashlib
import json
import os
from collections.abc import Mapping
from importlib import resources as importlib_resources
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
import yaml

from subslope.config.cdm import CDM_GRIDS, cdm_grids, cdm_scenes, cdm_series
from subslope.config.messages import describe

__all__ = [
    "ConfigError",
    "RUN_ONLY_RENDER_KEYS",
    "MIRROR_ENV_VAR",
    "schema_path",
    "load_schema",
    "safe_load_yaml",
    "schema_defaults",
    "fill_defaults",
    "validate",
    "cross_key_problems",
    "light_fit_enabled",
    "halo_free_sets",
    "halo_free_shards",
    "active_stages",
    "CDM_GRIDS",
    "cdm_grids",
    "cdm_scenes",
    "cdm_series",
    "missing_scene",
    "STAGE_NEEDS",
    "BASE_KEY",
    "deep_merge",
    "read_layers",
    "read_files",
    "load",
    "apply_env_overrides",
    "canonical_json",
    "config_hash",
]

#: Environment variable that overrides ``data.mirror``.
MIRROR_ENV_VAR = "SUBSLOPE_DATA_MIRROR"


class ConfigError(ValueError):
    """A configuration value is missing, of the wrong type or outside its allowed range."""


def schema_path() -> Path:
    """Path of the canonical configuration schema shipped inside the package."""
    return Path(str(importlib_resources.files("subslope") / "schemas" / "config.schema.yaml"))


#: PyYAML's safe loader, on libyaml where PyYAML was built with it (the same documents
#: and values, parsed ~10x faster: every job of a campaign reads the schema).
_SafeLoader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def safe_load_yaml(stream: Any) -> Any:
    """``yaml.safe_load`` of ``stream`` (text or file) with :data:`_SafeLoader`."""
    return yaml.load(stream, Loader=_SafeLoader)


@functools.lru_cache(maxsize=1)
def _schema() -> dict[str, Any]:
    with open(schema_path(), encoding="utf-8") as handle:
        return safe_load_yaml(handle)


def load_schema() -> dict[str, Any]:
    """The configuration schema as a dictionary (a copy of the one read per process)."""
    return copy.deepcopy(_schema())


def schema_defaults(section: str, schema: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """``{key: default}`` of the keys of a config section given by its dotted path
    (``"simulation.render"``, ``"instrument"``), from the schema."""
    node: Mapping[str, Any] = _schema() if schema is None else schema
    for part in section.split("."):
        try:
            node = node["properties"][part]
        except KeyError:
            raise ConfigError(f"the schema has no config section {section!r}") from None
    return {
        k: copy.deepcopy(v["default"])
        for k, v in node.get("properties", {}).items()
        if "default" in v
    }


def fill_defaults(
    config: Mapping[str, Any], schema: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """Return a deep copy of ``config`` with every missing key set to its schema default.

    Sections (objects) whose default is ``{}`` are created and then filled recursively,
    so an empty config yields the complete default configuration. Values of the wrong
    type are left alone for :func:`validate` to report.
    """
    schema = _schema() if schema is None else schema
    out = copy.deepcopy(dict(config))
    _fill(out, schema)
    return out


def _fill(instance: dict[str, Any], schema: Mapping[str, Any]) -> None:
    for key, sub in schema.get("properties", {}).items():
        if key not in instance and "default" in sub:
            instance[key] = copy.deepcopy(sub["default"])
        if isinstance(instance.get(key), dict) and "properties" in sub:
            _fill(instance[key], sub)


def validate(config: Mapping[str, Any], *, fill: bool = True) -> dict[str, Any]:
    """Validate ``config`` and return it with defaults filled: the one validation of a
    campaign configuration (the workflow and ``subslope validate-config`` both call it).

    First the schema (types, ranges, unknown keys), then every check that involves
    several keys (:func:`cross_key_problems`). Raises :class:`ConfigError` listing every
    problem, one per line, each naming its key and what is allowed. A config of plain
    JSON values is validated once per process (~0.9 s) and its result copied after that:
    a shard job, or a training stream simulating batch after batch, validates the same
    config many times.
    """
    if not isinstance(config, Mapping):
        raise ConfigError(
            f"the configuration must be a mapping of keys, got {type(config).__name__}"
        )
    try:  # a plain-JSON config (the common case) is validated once per process
        text = canonical_json(config)
        plain = bool(json.loads(text) == config)
    except (TypeError, ValueError):
        plain = False
    if plain:
        return copy.deepcopy(_validated(text, fill))
    return _validate(config, fill)


#: Validated configs by (canonical JSON, fill): the config as given and, since
#: validating a validated config returns it unchanged, the result itself.
_VALIDATED: dict[tuple[str, bool], dict[str, Any]] = {}


def _validated(text: str, fill: bool) -> dict[str, Any]:
    if (text, fill) not in _VALIDATED:
        full = _validate(json.loads(text), fill)
        if len(_VALIDATED) >= 128:
            _VALIDATED.clear()
        _VALIDATED[(text, fill)] = full
        _VALIDATED[(canonical_json(full), fill)] = full
    return _VALIDATED[(text, fill)]


def _validate(config: Mapping[str, Any], fill: bool) -> dict[str, Any]:
    schema = _schema()
    full = fill_defaults(config, schema) if fill else copy.deepcopy(dict(config))
    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(full), key=lambda e: [str(p) for p in e.absolute_path])
    problems = [describe(e) for e in errors] or cross_key_problems(full)
    if problems:
        lines = "\n".join("  - " + p for p in problems)
        raise ConfigError(f"invalid configuration ({len(problems)} problem(s)):\n{lines}")
    return full


#: The stages each stage needs (a stage runs only when it and all of these are on).
STAGE_NEEDS: dict[str, tuple[str, ...]] = {
    "gallery": (),
    "simulate": (),
    "domain": ("simulate",),
    "train": ("simulate",),
    "evaluate": ("train",),
    "calibrate": ("evaluate",),
    "cdm_grid": ("evaluate",),
    "null_tests": ("calibrate",),
    "hst": ("calibrate",),
    "figures": ("train",),
    "signal_budget": ("simulate",),
    "summary": ("figures",),
}


def active_stages(config: Mapping[str, Any]) -> dict[str, bool]:
    """``{stage: runs}``: a stage runs when its flag and the flags of every stage it needs
    (:data:`STAGE_NEEDS`) are on, so a switched-off stage never runs as a dependency."""
    flags = config["stages"]

    def on(name: str) -> bool:
        return bool(flags[name]) and all(on(need) for need in STAGE_NEEDS[name])

    return {name: on(name) for name in STAGE_NEEDS}


def _scene_value(config: Mapping[str, Any], scene: str, key: str) -> Any:
    """The value at dotted ``key`` of scene ``scene``: the config's, else its preset's,
    else the paper scene's (``schemas/scene_presets.yaml``)."""
    presets = _scene_presets()
    layers = [
        (config.get("scenes") or {}).get(scene) or {},
        presets["presets"].get(scene, {}),
        presets["paper_scene"],
    ]
    for layer in layers:
        value: Any = layer
        for part in key.split("."):
            value = value.get(part, _MISSING) if isinstance(value, Mapping) else _MISSING
        if value is not _MISSING:
            return value
    raise KeyError(f"scenes.{scene}.{key}")


_MISSING = object()


@functools.lru_cache(maxsize=1)
def _scene_presets() -> dict[str, Any]:
    with open(schema_path().with_name("scene_presets.yaml"), encoding="utf-8") as handle:
        return safe_load_yaml(handle)


def cross_key_problems(config: Mapping[str, Any]) -> list[str]:
    """Problems that involve several keys of a schema-valid ``config`` (defaults filled).

    Checked: the γ grid's order; every simulated scene's shard size against its
    ``images_per_set``; for the stages that run, the calibration and CDM scenes exist in
    ``simulation.scenes``, the calibrated stack sizes fit the stack scene's sets, and the
    CDM grid includes the prediction multiplier a = 1; the domain check's scene is
    simulated and its percentile bounds are ordered. What needs the scenes resolved (the
    matched controls, the abundance series) is checked by
    :func:`subslope.plan.plan_problems`.
    """
    problems: list[str] = []
    grid = config["inference"]["gamma_grid"]
    if not grid["low"] < grid["high"]:
        problems.append(
            f"config keys inference.gamma_grid.low/high = {grid['low']!r}/{grid['high']!r}: "
            "need low < high"
        )
    for name, counts in config["simulation"]["scenes"].items():
        per_set = _scene_value(config, name, "images_per_set")
        if isinstance(per_set, int) and per_set > 0 and counts["images_per_shard"] % per_set:
            problems.append(
                f"config key simulation.scenes.{name}.images_per_shard = "
                f"{counts['images_per_shard']} "
                f"must be a multiple of scenes.{name}.images_per_set = {per_set}"
            )
    stages = active_stages(config)
    cal = config["calibration"]
    if stages["train"] and config["training"]["data"] == "stream":
        problems += _stream_problems(config)
    problems += _inputs_problems(config)
    if stages["calibrate"]:
        problems += missing_scene(config, "calibration.single_scene", cal["single_scene"])
        stack = missing_scene(config, "calibration.stack_scene", cal["stack_scene"])
        problems += stack
        per_set = None if stack else _scene_value(config, cal["stack_scene"], "images_per_set")
        too_big = [n for n in cal["n_images"] if per_set and n > 1 and n > per_set]
        if too_big:
            problems.append(
                f"config key calibration.n_images = {sorted(cal['n_images'])}: N > 1 must not "
                f"exceed the images_per_set = {per_set} of calibration.stack_scene "
                f"{cal['stack_scene']!r} (too large: {too_big})"
            )
    if stages["cdm_grid"]:
        problems += _cdm_problems(config)
    if stages["null_tests"]:
        for k, name in enumerate(config["null_tests"]["scenes"]):
            problems += missing_scene(config, f"null_tests.scenes[{k}]", name)
        if stages["calibrate"] and cal["stack_scene"] in shard_scenes(config):
            problems += _halo_free_problems(config)
    if stages["domain"]:
        problems += missing_scene(config, "domain.scene", config["domain"]["scene"])
        lo, hi = config["domain"]["bounds"]
        if not lo < hi:
            problems.append(f"config key domain.bounds = {[lo, hi]}: need low < high")
    return problems


def missing_scene(config: Mapping[str, Any], key: str, name: str) -> list[str]:
    """The problem, if any, of config ``key`` naming scene ``name`` that has no shards."""
    with_shards = shard_scenes(config)
    if name in with_shards:
        return []
    why = (
        " (training.data = stream: its images are simulated while training)"
        if name in config["simulation"]["scenes"]
        else ""
    )
    return [
        f"config key {key} = {name!r}: no shards of that scene{why}; simulated scenes "
        f"with shards (simulation.scenes): {', '.join(sorted(with_shards)) or 'none'}"
    ]


def _cdm_problems(config: Mapping[str, Any]) -> list[str]:
    """The CDM stage's scenes have shards, the grid includes a = 1, and a reference
    grid has its NFW scene wherever its tNFW scene or its controls are set."""
    cdm = config["cdm"]
    problems = missing_scene(config, "cdm.nfw_scene", cdm["nfw_scene"])
    if not problems:
        mults = config["simulation"]["multipliers"] or _scene_value(
            config, cdm["nfw_scene"], "concentration.multipliers"
        )
        if 1.0 not in [float(a) for a in mults]:
            problems.append(
                f"config key simulation.multipliers = {list(mults)} must include 1.0 "
                "(the CDM prediction, a = 1)"
            )
    for key in ("tnfw_scene", "reference_nfw_scene", "reference_tnfw_scene"):
        if cdm[key]:
            problems += missing_scene(config, f"cdm.{key}", cdm[key])
    if cdm["reference_tnfw_scene"] and not cdm["reference_nfw_scene"]:
        problems.append(
            "config key cdm.reference_tnfw_scene is set but cdm.reference_nfw_scene is "
            "null: the reference grid needs its NFW scene"
        )
    for key, name, kind in cdm_series(config):
        if kind in CDM_GRIDS and kind not in cdm_grids(config):
            problems.append(
                f"config key {key} = {name!r}: the reference grid is off "
                "(cdm.reference_nfw_scene: null)"
            )
        else:
            problems += missing_scene(config, key, name)
    return problems


def _inputs_problems(config: Mapping[str, Any]) -> list[str]:
    """``training.inputs`` against ``simulation.light_fit``."""
    if (
        config["training"]["inputs"] == "light_subtracted"
        and config["simulation"]["light_fit"] is False
    ):
        return [
            "config key simulation.light_fit = false: training.inputs = 'light_subtracted' "
            "needs the lens-light fit of every image (auto or true)"
        ]
    return []


def halo_free_sets(config: Mapping[str, Any]) -> int:
    """Sets of ``calibration.stack_scene`` the halo-free null test re-renders:
    ``null_tests.halo_free_sets``, or all the scene's sets where it holds fewer (the
    summary states the number used); 0 when the test is off."""
    scene = config["calibration"]["stack_scene"]
    sim = config["simulation"]["scenes"].get(scene)
    if not sim:
        return 0
    per_set = int(_scene_value(config, scene, "images_per_set"))
    have = int(sim["n_shards"]) * (int(sim["images_per_shard"]) // per_set)
    return min(int(config["null_tests"]["halo_free_sets"]), have)


def halo_free_shards(config: Mapping[str, Any]) -> int:
    """How many shards of ``calibration.stack_scene`` (from the first) hold the
    :func:`halo_free_sets` sets."""
    n_sets = halo_free_sets(config)
    if n_sets == 0:
        return 0
    scene = config["calibration"]["stack_scene"]
    per_set = int(_scene_value(config, scene, "images_per_set"))
    per_shard = int(config["simulation"]["scenes"][scene]["images_per_shard"])
    return -(-n_sets // max(1, per_shard // per_set))


def _halo_free_problems(config: Mapping[str, Any]) -> list[str]:
    """The shards of ``calibration.stack_scene`` must hold whole sets for the test."""
    scene = config["calibration"]["stack_scene"]
    sim = config["simulation"]["scenes"][scene]
    per_set = int(_scene_value(config, scene, "images_per_set"))
    if config["null_tests"]["halo_free_sets"] and sim["images_per_shard"] % per_set:
        return [
            f"config key null_tests.halo_free_sets = {config['null_tests']['halo_free_sets']}: "
            f"the shards of calibration.stack_scene {scene!r} must hold whole sets "
            f"(images_per_shard = {sim['images_per_shard']} is not a multiple of "
            f"images_per_set = {per_set}); 0 switches the test off"
        ]
    return []


def light_fit_enabled(config: Mapping[str, Any]) -> bool:
    """Whether shard jobs fit and store the lens light of every image
    (``simulation.light_fit``: ``auto`` = when ``training.inputs`` is ``light_subtracted``)."""
    choice = config["simulation"]["light_fit"]
    if choice == "auto":
        return config["training"]["inputs"] == "light_subtracted"
    return bool(choice)


#: The scene whose images ``training.data: stream`` simulates while training.
STREAMED_SCENE = "train"


def shard_scenes(config: Mapping[str, Any]) -> list[str]:
    """The scenes of ``simulation.scenes`` that have shards: all of them, but the
    :data:`STREAMED_SCENE` when the estimator trains on a stream (``training.data:
    stream``) and the train stage runs."""
    scenes = list(config["simulation"]["scenes"])
    streamed = config.get("training", {}).get("data") == "stream" and active_stages(config)["train"]
    return [s for s in scenes if not (streamed and s == STREAMED_SCENE)]


def _stream_problems(config: Mapping[str, Any]) -> list[str]:
    """What ``training.data: stream`` needs: an epoch of at least one batch and fixed
    validation shards."""
    problems = []
    simulated = config["simulation"]["scenes"]
    epoch = simulated[STREAMED_SCENE]["n_shards"] * simulated[STREAMED_SCENE]["images_per_shard"]
    if epoch < config["training"]["batch_size"]:
        problems.append(
            f"config key training.data = 'stream': an epoch holds simulation.scenes."
            f"{STREAMED_SCENE}.n_shards x images_per_shard = {epoch} images, fewer than "
            f"one batch (training.batch_size = {config['training']['batch_size']})"
        )
    if not simulated["validation"]["n_shards"]:
        problems.append(
            "config key training.data = 'stream' needs validation shards "
            "(simulation.scenes.validation.n_shards >= 1): the stream never repeats an "
            "image, early stopping compares epochs on the validation shards"
        )
    return problems


def apply_env_overrides(config: dict[str, Any]) -> dict[str, Any]:
    """Apply environment overrides in place (``SUBSLOPE_DATA_MIRROR`` → ``data.mirror``)."""
    value = os.environ.get(MIRROR_ENV_VAR)
    if value:
        config.setdefault("data", {})["mirror"] = value
    return config


#: Top-level key of a config file naming the file it is layered over (relative to it).
BASE_KEY = "base"

#: Keys of ``simulation.render`` that change where and how fast a shard is made, never
#: its bits: left out of a shard job's params, of the config a shard records and of its
#: cache key, so changing one reruns no shard.
RUN_ONLY_RENDER_KEYS = ("device", "compile_cache")


#: The key that marks a mapping as a prior (``{dist: ..., ...}``): such a mapping replaces
#: the value beneath it whole, so that no bound of an older prior survives in a new one.
PRIOR_KEY = "dist"


def deep_merge(base: Mapping[str, Any], top: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``top`` merged in: mappings key by key, except a prior (a mapping
    with :data:`PRIOR_KEY`), which replaces whatever it lands on whole; any other value
    replaced."""
    out = copy.deepcopy(dict(base))
    for key, value in top.items():
        if (
            isinstance(value, Mapping)
            and PRIOR_KEY not in value
            and isinstance(out.get(key), Mapping)
        ):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        with open(path, encoding="utf-8") as handle:
            raw = safe_load_yaml(handle)
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {path}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {path} is not valid YAML: {exc}") from None
    raw = {} if raw is None else raw
    if not isinstance(raw, Mapping):
        raise ConfigError(
            f"config file {path} must hold a mapping of keys, not {type(raw).__name__}"
        )
    return dict(raw)


def read_layers(path: str | os.PathLike[str], _seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """The raw keys of a config file with the files it is layered over.

    A file's ``base: other.yaml`` (a path relative to the file) names the file it sits on:
    that file's keys are read first (with its own base, if any) and this file's keys are
    merged over them (:func:`deep_merge`). A file without ``base`` sits on the schema
    defaults alone. This is the one way a config file is read: ``snakemake
    --configfile F``, ``subslope <command> --config F`` and ``subslope validate-config F``
    all see the same campaign.
    """
    path = Path(path)
    if path.resolve() in _seen:
        chain = " -> ".join(str(p) for p in (*_seen, path.resolve()))
        raise ConfigError(f"config key {BASE_KEY} of {path} makes a cycle: {chain}")
    raw = _read_yaml(path)
    base = raw.pop(BASE_KEY, None)
    if base is None:
        return raw
    if not isinstance(base, str) or not base:
        raise ConfigError(
            f"config key {BASE_KEY} = {base!r} in {path}: need the path of a config file "
            "(relative to this file)"
        )
    base_path = path.parent / base
    if not base_path.is_file():
        raise ConfigError(f"config key {BASE_KEY} = {base!r} in {path}: no such file {base_path}")
    return deep_merge(read_layers(base_path, (*_seen, path.resolve())), raw)


def read_files(paths) -> dict[str, Any]:
    """The raw keys of several config files merged in order, each with its layers
    (:func:`read_layers`): what ``snakemake --configfile A B`` and ``load([A, B])`` read."""
    raw: dict[str, Any] = {}
    for p in paths:
        raw = deep_merge(raw, read_layers(p))
    return raw


def load(
    path: str | os.PathLike[str] | list[str | os.PathLike[str]],
    *,
    overrides: Mapping[str, Any] | None = None,
    env: bool = True,
) -> dict[str, Any]:
    """Read config file(s), fill defaults, validate, and apply environment overrides.

    Parameters
    ----------
    path:
        YAML file, or several merged in order (an empty file means "all defaults");
        each is read with the files it names under ``base`` (:func:`read_layers`).
    overrides:
        Keys merged over the files (``snakemake --config key=value``).
    env:
        Apply :func:`apply_env_overrides` after validation (default True).
    """
    paths = [path] if isinstance(path, (str, os.PathLike)) else list(path)
    raw = deep_merge(read_files(paths), overrides or {})
    try:
        config = validate(raw)
    except ConfigError as exc:
        raise ConfigError(f"{', '.join(str(p) for p in paths)}: {exc}") from None
    return apply_env_overrides(config) if env else config


def canonical_json(obj: Any) -> str:
    """Deterministic JSON (sorted keys, no spaces, numpy scalars as Python numbers)."""

    def default(o):
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, (Path,)):
            return str(o)
        raise TypeError(f"not JSON serialisable: {type(o).__name__}")

    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=default, allow_nan=False)


def config_hash(sections: Mapping[str, Any]) -> str:
    """SHA-256 (hex) of the canonical JSON of ``sections``."""
    return hashlib.sha256(canonical_json(sections).encode()).hexdigest()
