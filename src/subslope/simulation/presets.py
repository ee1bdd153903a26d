"""Scene presets (``schemas/scene_presets.yaml``) and how a config's scene entry is
merged onto its preset: key by key, a prior mapping (one with ``dist``) replacing the
preset's whole, unknown keys refused by name."""

from __future__ import annotations

import copy
from collections.abc import Mapping
from typing import Any

from subslope.simulation.spec_checks import SceneError

__all__ = [
    "LENS_LIGHT_PRIORS",
    "OPTIONAL_KEYS",
    "PAPER_SCENE",
    "PRESETS",
    "merge_onto_preset",
    "preset",
]


def _load_presets() -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    from importlib import resources as importlib_resources

    from subslope.config import safe_load_yaml

    text = (importlib_resources.files("subslope") / "schemas" / "scene_presets.yaml").read_text(
        encoding="utf-8"
    )
    doc = safe_load_yaml(text)
    return doc["paper_scene"], doc["presets"], doc["lens_light_priors"]


#: The training scene of the reference paper, the overrides of the named scenes and the
#: named lens-light priors (``schemas/scene_presets.yaml``, where each value is commented).
PAPER_SCENE, PRESETS, LENS_LIGHT_PRIORS = _load_presets()


def _is_prior(d: Any) -> bool:
    return isinstance(d, Mapping) and "dist" in d


def _merge(base: dict[str, Any], over: Mapping[str, Any], key: str) -> dict[str, Any]:
    """Merge ``over`` onto ``base``; unknown keys raise; prior mappings replace whole."""
    if not isinstance(over, Mapping):
        raise SceneError(f"config key {key} = {over!r} must be a mapping")
    out = copy.deepcopy(base)
    for k, v in over.items():
        sub = f"{key}.{k}"
        if k not in base:
            raise SceneError(
                f"unknown config key {sub}; allowed keys at {key}: {', '.join(sorted(base))}"
            )
        if isinstance(base[k], Mapping) and not _is_prior(base[k]) and isinstance(v, Mapping):
            out[k] = _merge(base[k], v, sub)
        else:
            out[k] = copy.deepcopy(v)
    return out


def preset(name: str) -> dict[str, Any]:
    """Complete config mapping of the preset scene ``name`` (``train`` for other names)."""
    return _merge(PAPER_SCENE, PRESETS.get(name, {}), f"scenes.{name}")


#: Scene keys a preset does not hold: they appear in a scene's mapping (and its shards'
#: hash) only where a config sets them. ``common_draws``: the shards draw the CDM scenes'
#: sets (seed keyed by :data:`subslope.simulation.shard.CDM_DRAWS`); ``subhalos.
#: fixed_gamma``: every set's label γ, drawn from ``subhalos.gamma`` and then replaced,
#: so that the scene's random streams stay those of a scene with a free label (the
#: matched EPL control of figure 4).
OPTIONAL_KEYS = (("common_draws",), ("subhalos", "fixed_gamma"))


def merge_onto_preset(name: str, spec: Mapping[str, Any] | None, key: str) -> dict[str, Any]:
    """The complete mapping of scene ``name``: ``spec`` merged onto its preset, after the
    named lens-light prior ``spec.lens_light.prior`` (:data:`LENS_LIGHT_PRIORS`); the
    :data:`OPTIONAL_KEYS` that ``spec`` sets are added."""
    if isinstance(spec, Mapping):
        spec = copy.deepcopy(dict(spec))
        optional = []
        for path in OPTIONAL_KEYS:
            node = spec
            for part in path[:-1]:
                node = node.get(part) if isinstance(node, Mapping) else None
            if isinstance(node, dict) and path[-1] in node:
                optional.append((path, node.pop(path[-1])))
        merged = _merge_preset(name, spec, key)
        for path, value in optional:
            node = merged
            for part in path[:-1]:
                node = node[part]
            node[path[-1]] = value
        return merged
    return _merge_preset(name, spec, key)


def _merge_preset(name: str, spec: Mapping[str, Any] | None, key: str) -> dict[str, Any]:
    base = preset(name)
    light = (spec or {}).get("lens_light") if isinstance(spec, Mapping) else None
    if isinstance(light, Mapping) and "prior" in light:
        named = light["prior"]
        if named not in LENS_LIGHT_PRIORS:
            raise SceneError(
                f"config key {key}.lens_light.prior = {named!r}; allowed: "
                f"{', '.join(sorted(LENS_LIGHT_PRIORS))}"
            )
        base["lens_light"].update(copy.deepcopy(LENS_LIGHT_PRIORS[named]))
    return _merge(base, spec or {}, key)
