"""Messages for configs that fail the schema: each names the key, the value and what is
allowed (:func:`describe`, used by :func:`subslope.config.validate`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import jsonschema

__all__ = ["key_path", "allowed", "describe"]


def key_path(parts) -> str:
    return ".".join(str(p) for p in parts) or "<top level>"


def allowed(schema: Mapping[str, Any]) -> str:
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
        left = "(" if "exclusiveMinimum" in schema or lo is None else "["
        right = ")" if "exclusiveMaximum" in schema or hi is None else "]"
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


def describe(error: jsonschema.ValidationError, prefix: tuple = ()) -> str:
    """One line for a schema error: the key (``prefix`` + the error's path), its value and
    what is allowed. A prior (a mapping with ``dist``) that matches none of the prior
    forms is described by the form its ``dist`` names."""
    path = [*prefix, *error.absolute_path]
    if error.validator == "oneOf" and isinstance(error.instance, Mapping):
        if "dist" in error.instance:
            return _prior_problem(error, path)
    if error.validator == "additionalProperties":
        known = set(error.schema.get("properties", {}))
        unknown = sorted(k for k in error.instance if k not in known)
        keys = ", ".join(key_path(path + [k]) for k in unknown)
        return f"unknown config key(s) {keys}; allowed keys at {key_path(path)}: " + ", ".join(
            sorted(known)
        )
    if error.validator == "required":
        return f"config key {key_path(path)}: {error.message}"
    # The failing keyword sits in error.schema; the bounds/types of the whole key are in
    # the parent schema of that keyword, which for our flat schema is error.schema itself.
    return (
        f"config key {key_path(path)} = {error.instance!r} is not allowed "
        f"(failed '{error.validator}'); allowed: {allowed(error.schema)}"
    )


def _prior_problem(error: jsonschema.ValidationError, path: list) -> str:
    """What is wrong with a prior mapping: its ``dist`` unknown, or the keys that the form
    of its ``dist`` does not allow."""
    forms = {
        b["properties"]["dist"]["const"]: b
        for b in error.validator_value
        if isinstance(b, Mapping) and "dist" in b.get("properties", {})
    }
    dist = error.instance["dist"]
    form = forms.get(dist) if isinstance(dist, str) else None
    if form is None:
        return (
            f"config key {key_path([*path, 'dist'])} = {dist!r} is not a prior; allowed: "
            + ", ".join(repr(d) for d in forms)
        )
    inner = jsonschema.Draft202012Validator(form).iter_errors(error.instance)
    lines = [describe(e, tuple(path)) for e in inner]
    keys = ", ".join(sorted(form["properties"]))
    return "; ".join(lines) + f" (a {dist} prior takes {keys})"
