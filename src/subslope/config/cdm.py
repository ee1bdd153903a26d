"""The concentration grids of a config and the scenes its CDM stage measures beside
them (matched EPL controls, extra scenes, the abundance series): plain reads of the
``cdm`` section, no validation."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

__all__ = ["CDM_GRIDS", "cdm_grids", "cdm_scenes", "cdm_series"]

#: Names of the concentration grids (figure 4's panels) in :func:`cdm_grids`.
CDM_GRIDS = ("field", "reference")


def cdm_grids(config: Mapping[str, Any]) -> dict[str, tuple[str, str | None]]:
    """The concentration grids of a config, ``{grid: (nfw_scene, tnfw_scene)}``: ``field``
    (``cdm.nfw_scene``/``tnfw_scene``, always) and ``reference``
    (``cdm.reference_nfw_scene``/``reference_tnfw_scene``, when set: the reference
    code's sets)."""
    cdm = config["cdm"]
    grids = {"field": (cdm["nfw_scene"], cdm["tnfw_scene"])}
    if cdm.get("reference_nfw_scene"):
        grids["reference"] = (cdm["reference_nfw_scene"], cdm.get("reference_tnfw_scene"))
    return grids


def cdm_scenes(config: Mapping[str, Any]) -> list[str]:
    """Every CDM scene of :func:`cdm_grids`, in grid order, then ``cdm.extra_scenes``,
    without repeats."""
    names = [s for pair in cdm_grids(config).values() for s in pair if s]
    return list(dict.fromkeys(names + list(config["cdm"].get("extra_scenes") or ())))


def cdm_series(config: Mapping[str, Any]) -> list[tuple[str, str, str]]:
    """``(key, scene, kind)`` of every scene the CDM stage measures beside its grids:
    kind ``field``/``reference`` (a matched EPL control of that grid), ``extra`` or
    ``abundance``."""
    cdm = config["cdm"]
    out = [
        (f"cdm.{grid}_controls[{k}]", name, grid)
        for grid in CDM_GRIDS
        for k, name in enumerate(cdm[f"{grid}_controls"])
    ]
    for kind, key in (("extra", "extra_scenes"), ("abundance", "abundance")):
        out += [(f"cdm.{key}[{k}]", name, kind) for k, name in enumerate(cdm[key])]
    return out
