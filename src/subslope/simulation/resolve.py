"""The scenes of a config: each scene resolved against its preset, the multipliers a CDM
scene is simulated at, and the config values that determine a shard's images (hashed
into its checksum and its job's parameters)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from subslope.config import RUN_ONLY_RENDER_KEYS
from subslope.simulation.presets import merge_onto_preset
from subslope.simulation.scenes import Scene

__all__ = [
    "MULTIPLIER_RTOL",
    "resolved_scene",
    "same_multiplier",
    "scene_multipliers",
    "simulation_sections",
]

#: Relative tolerance within which two concentration multipliers are one value (the
#: config's floats, the shards' attributes and the tables' columns all round-trip well
#: within it): the one test of multiplier equality.
MULTIPLIER_RTOL = 1e-9


def same_multiplier(values, a: float):
    """Whether ``values`` (a multiplier, or an array or column of them) equal the
    multiplier ``a`` within :data:`MULTIPLIER_RTOL` (elementwise for arrays)."""
    return np.isclose(
        np.asarray(values, dtype=np.float64), float(a), rtol=MULTIPLIER_RTOL, atol=0.0
    )


def resolved_scene(config: Mapping[str, Any], name: str) -> tuple[Scene, dict[str, Any]]:
    """The Scene ``name`` of the config and its complete spec (preset merged, JSON-able)."""
    spec = (config.get("scenes") or {}).get(name) or {}
    key = f"scenes.{name}"
    merged = merge_onto_preset(name, spec, key)
    return Scene.from_config(name, spec, key), merged


def scene_multipliers(config: Mapping[str, Any], scene: Scene) -> tuple[float, ...] | None:
    """Multipliers simulated for a CDM scene (None for scenes without concentrations):
    its own ``simulation.scenes.<name>.multipliers``, else ``simulation.multipliers``,
    else the scene's ``concentration.multipliers``."""
    if not scene.uses_concentration:
        return None
    own = ((config["simulation"].get("scenes") or {}).get(scene.name) or {}).get("multipliers")
    mults = own or config["simulation"].get("multipliers")
    return tuple(float(a) for a in (mults if mults else scene.concentration.multipliers))


def simulation_sections(config: Mapping[str, Any], scene: str) -> dict[str, Any]:
    """The config values that determine the images of a shard of ``scene`` (hashed).

    ``config`` is validated first, so omitted keys count with their defaults."""
    from subslope import config as _config

    config = _config.validate(config)
    _, spec = resolved_scene(config, scene)
    sim = config["simulation"]
    render = {k: v for k, v in sim["render"].items() if k not in RUN_ONLY_RENDER_KEYS}
    sections = {
        "seed": config["seed"],
        "instrument": config["instrument"],
        "cosmology": config["cosmology"],
        "scene": spec,
        "images_per_shard": sim["scenes"][scene]["images_per_shard"]
        if scene in sim["scenes"]
        else None,
        "multipliers": sim["multipliers"],
        "render": render,
        "sources": sim["sources"],
    }
    if _config.light_fit_enabled(config):
        # The stored lens-light fit starts at the measured light centre.
        sections["light_fit"] = {"lens_centre": config["hst"]["lens_centre"]}
    return sections
