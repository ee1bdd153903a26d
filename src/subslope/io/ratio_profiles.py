"""Profiles files: ln r̂(x|γ) of every image of one evaluated shard on the γ grid.

One HDF5 file per evaluated shard holds ``log_ratio (B, G)`` (float64), ``gammas (G,)``,
``gamma_true (B,)`` (NaN for CDM scenes, which have no label), ``set_index (B,)``
(images of one set share γ), ``c_multiplier (B,)`` (NaN for EPL scenes), ``theta_e``,
``lens_x``, ``lens_y`` (the mask geometry used) and attributes naming the scene, shard,
estimator and run. Every dataset carries a Fletcher-32 checksum per chunk, as the shards
do: a flipped byte or a truncated file is a :class:`ProfilesError` naming the file, the
dataset and the first row that cannot be read, never a silently different number.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from subslope.io.atomic import atomic_write

__all__ = ["PROFILE_FIELDS", "ProfilesError", "write_profiles", "read_profiles"]


class ProfilesError(ValueError):
    """A profiles file is missing, truncated or corrupt (the message names it)."""


def _recovery(path) -> str:
    return f"delete {path} and run snakemake again to evaluate it anew"


def _rows(path, fh: h5py.File, name: str) -> np.ndarray:
    """Dataset ``name`` of an open profiles file, every chunk checked; a bad chunk raises
    :class:`ProfilesError` naming file, dataset and the first row that cannot be read."""
    if name not in fh:
        raise ProfilesError(f"{path} lacks dataset {name}: not a profiles file; {_recovery(path)}")
    data = fh[name]
    try:
        return data[...]
    except OSError as exc:
        for k in range(data.shape[0] if data.shape else 0):
            try:
                data[k]
            except OSError:
                raise ProfilesError(
                    f"{path}: {name} row {k} cannot be read ({exc}): the file is corrupt; "
                    f"{_recovery(path)}"
                ) from None
        raise ProfilesError(f"{path}: {name} cannot be read ({exc}); {_recovery(path)}") from None


#: Datasets of a profiles file (besides ``gammas``).
PROFILE_FIELDS = (
    "log_ratio",
    "gamma_true",
    "set_index",
    "c_multiplier",
    "theta_e",
    "lens_x",
    "lens_y",
)


def write_profiles(
    path,
    *,
    log_ratio,
    gammas,
    gamma_true=None,
    set_index=None,
    c_multiplier=None,
    theta_e=None,
    lens_x=None,
    lens_y=None,
    attrs: Mapping[str, Any] | None = None,
) -> Path:
    """Write one profiles file atomically (:func:`subslope.io.atomic.atomic_write`)."""
    path = Path(path)
    lr = np.asarray(log_ratio, dtype=np.float64)
    g = np.asarray(gammas, dtype=np.float64)
    if lr.ndim != 2 or lr.shape[1] != g.size:
        raise ValueError(f"log_ratio must have shape (B, G={g.size}), got {lr.shape}")
    b = lr.shape[0]

    def col(v, dtype, fill):
        a = np.full(b, fill, dtype=dtype) if v is None else np.asarray(v, dtype=dtype)
        if a.shape != (b,):
            raise ValueError(f"per-image arrays must have shape ({b},), got {a.shape}")
        return a

    data = {
        "log_ratio": lr,
        "gamma_true": col(gamma_true, np.float64, np.nan),
        "set_index": col(set_index, np.int64, 0)
        if set_index is not None
        else np.arange(b, dtype=np.int64),
        "c_multiplier": col(c_multiplier, np.float64, np.nan),
        "theta_e": col(theta_e, np.float64, np.nan),
        "lens_x": col(lens_x, np.float64, np.nan),
        "lens_y": col(lens_y, np.float64, np.nan),
    }
    with atomic_write(path) as tmp, h5py.File(tmp, "w") as fh:
        for k, v in {"gammas": g, **data}.items():
            fh.create_dataset(k, data=v, fletcher32=v.size > 0, chunks=True if v.size else None)
        for k, v in (attrs or {}).items():
            fh.attrs[k] = (
                v if isinstance(v, (int, float, str, np.number)) else json.dumps(v, default=str)
            )
    return path


def read_profiles(paths) -> dict[str, np.ndarray]:
    """Concatenate profiles files: every field of :data:`PROFILE_FIELDS`, ``gammas`` and
    ``set_id`` (a set id unique across the files: ``set_index`` made distinct per file)."""
    paths = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    if not paths:
        raise ValueError("read_profiles: no files")
    parts: dict[str, list[np.ndarray]] = {k: [] for k in PROFILE_FIELDS}
    set_id = []
    gammas = None
    offset = 0
    for p in paths:
        if not Path(p).is_file():
            raise ProfilesError(f"profiles file not found: {p}")
        try:
            fh = h5py.File(p, "r")
        except OSError as exc:
            raise ProfilesError(
                f"{p} is not a readable HDF5 file (truncated or corrupt: {exc}); {_recovery(p)}"
            ) from None
        with fh:
            g = _rows(p, fh, "gammas")
            if gammas is None:
                gammas = g
            elif g.shape != gammas.shape or not np.allclose(g, gammas):
                raise ValueError(f"{p}: gamma grid differs from the first file's")
            for k in PROFILE_FIELDS:
                parts[k].append(_rows(p, fh, k))
        _, inv = np.unique(parts["set_index"][-1], return_inverse=True)
        set_id.append(inv.astype(np.int64) + offset)
        offset += int(inv.max()) + 1 if inv.size else 0
    out = {k: np.concatenate(v) for k, v in parts.items()}
    out["gammas"] = gammas
    out["set_id"] = np.concatenate(set_id)
    return out
