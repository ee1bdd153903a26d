"""Checks of scene config values: each returns the value or raises
:class:`SceneError` naming the full config key, the value and what is allowed."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from subslope.simulation.priors import Prior, PriorError

__all__ = ["SceneError", "prior_at", "choice", "real", "boolean", "within"]


class SceneError(PriorError):
    """A scene configuration is malformed; the message names the config key."""


def prior_at(d: Mapping[str, Any], k: str, key: str) -> Prior:
    """The prior ``d[k]`` (config key ``key.k``)."""
    return Prior.from_config(d[k], f"{key}.{k}")


def choice(value: Any, allowed: tuple[str, ...], key: str) -> str:
    """``value`` if it is one of ``allowed``."""
    if value not in allowed:
        raise SceneError(
            f"config key {key} = {value!r} is not allowed; allowed: {', '.join(allowed)}"
        )
    return value


def real(value: Any, key: str, lo: float, hi: float, lo_open=False, hi_open=False) -> float:
    """``value`` as a float if it is a finite number in the (half-)open interval."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok:
        ok = (value > lo if lo_open else value >= lo) and (value < hi if hi_open else value <= hi)
    if not ok:
        left, right = "(" if lo_open else "[", ")" if hi_open else "]"
        raise SceneError(
            f"config key {key} = {value!r} must be a number in {left}{lo}, {hi}{right}"
        )
    return float(value)


def boolean(value: Any, key: str) -> bool:
    """``value`` if it is a bool."""
    if not isinstance(value, bool):
        raise SceneError(f"config key {key} = {value!r} must be true or false")
    return value


def within(p: Prior, key: str, lo: float, hi: float, open_: bool = False) -> Prior:
    """``p`` if its support lies within [lo, hi] (``open_``: within (lo, hi))."""
    s_lo, s_hi = p.support
    if (s_lo <= lo or s_hi >= hi) if open_ else (s_lo < lo or s_hi > hi):
        where = f"({lo}, {hi})" if open_ else f"[{lo}, {hi}]"
        raise SceneError(
            f"config key {key}: support [{s_lo}, {s_hi}] of the prior must lie within {where}"
        )
    return p
