"""Stage ``cdm_grid``: stack MLEs of the simulated CDM sets per concentration
multiplier, their bands, the sets' effective subhalo slopes (the reference each reading
should approach, :mod:`subslope.physics.effective_slope`) and figure 4 (rules
effective_slope and measure_cdm_grid)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from subslope.figures.save import save_figure
from subslope.io.atomic import atomic_write, write_text
from subslope.io.ratio_profiles import read_profiles
from subslope.stages.calibrate import set_stacks

__all__ = [
    "GRID_COLUMNS",
    "EFFECTIVE_SLOPE_COLUMNS",
    "set_effective_slopes",
    "effective_slope_table",
    "measure_cdm_grid",
    "cdm_band",
]

#: Columns of ``cdm_grid.csv``, one row per (scene, multiplier).
GRID_COLUMNS = (
    "scene",
    "multiplier",
    "n_sets",
    "n_images",
    "median",
    "lo",
    "hi",
    "reference",
    "distance",
)

#: Columns of ``effective_slope.csv``, one row per simulated set.
EFFECTIVE_SLOPE_COLUMNS = ("scene", "multiplier", "shard", "set_index", "n_subhalos", "gamma_eff")


def set_effective_slopes(shard_path, radii=None) -> list[dict]:
    """Signal-weighted effective slope (:func:`subslope.physics.effective_slope.population_slope`)
    of the subhalos of every set of a (t)NFW shard, from the stored populations.

    Returns one dict per set: ``set_index``, ``n_subhalos``, ``gamma_eff`` (NaN for a set
    without subhalos)."""
    from subslope.io.shards import open_shard
    from subslope.physics.effective_slope import effective_slopes, population_slope
    from subslope.simulation.rerender import stored_populations

    with open_shard(shard_path) as shard:
        profile = shard.attrs["subhalo_profile"]
        if profile not in ("nfw", "tnfw"):
            raise ValueError(f"{shard_path}: subhalo profile {profile!r}, need nfw or tnfw")
        idx = np.arange(len(shard))
        macro = {k: v[idx] for k, v in shard.params.items() if k != "noise_seed"}
        subs, _ = stored_populations(shard, idx, macro)
    sets = np.asarray(macro["set_index"])
    labels = np.unique(sets)
    if subs is None or not subs.counts.sum():
        return [{"set_index": int(s), "n_subhalos": 0, "gamma_eff": np.nan} for s in labels]
    g, w = effective_slopes(profile, subs.r_s, subs.alpha_rs, subs.r_t, radii)
    member_set = np.repeat(sets, subs.counts)
    got, slopes = population_slope(g, w, member_set)
    by_set = dict(zip(got.tolist(), slopes.tolist()))
    n_by_set = np.bincount(np.searchsorted(labels, member_set), minlength=labels.size)
    return [
        {"set_index": int(s), "n_subhalos": int(n), "gamma_eff": by_set.get(int(s), np.nan)}
        for s, n in zip(labels, n_by_set)
    ]


def effective_slope_table(groups: Sequence, out_csv, radii=None):
    """Rule effective_slope: :func:`set_effective_slopes` of every ``(scene, multiplier,
    shard path)`` of ``groups``, one row per set in ``out_csv``. Returns the table."""
    import pandas as pd

    rows = []
    for scene, multiplier, path in groups:
        shard = int(Path(path).stem.rsplit("_", 1)[-1])
        for r in set_effective_slopes(path, radii):
            rows.append({"scene": scene, "multiplier": float(multiplier), "shard": shard, **r})
    write_text(
        out_csv, pd.DataFrame(rows, columns=list(EFFECTIVE_SLOPE_COLUMNS)).to_csv(index=False)
    )
    return pd.DataFrame(rows, columns=list(EFFECTIVE_SLOPE_COLUMNS))


def _reference(slopes, scene: str, multipliers, band) -> np.ndarray | None:
    """(3, n_a) rows lo, median, hi of the sets' effective slopes of ``scene``."""
    if slopes is None:
        return None
    out = np.full((3, len(multipliers)), np.nan)
    for i, a in enumerate(multipliers):
        sel = slopes[(slopes["scene"] == scene) & np.isclose(slopes["multiplier"], a)]
        g = sel["gamma_eff"].to_numpy(dtype=np.float64)
        g = g[np.isfinite(g)]
        if g.size:
            out[:, i] = np.percentile(g, [band[0], 50, band[1]])
    return out


def _scene_grid(files, scene: str, mults, band, slopes) -> tuple[list[dict], np.ndarray]:
    """The table rows of ``scene`` (one per multiplier with sets) and its (n_a, n_sets)
    stack MLEs, padded with NaN."""
    rows, per_a = [], []
    for a in mults:
        paths = files.get((scene, a))
        if not paths:
            per_a.append(np.array([]))
            continue
        st = set_stacks(read_profiles(paths))
        per_a.append(st["mle"])
        lo, med, hi = np.percentile(st["mle"], [band[0], 50, band[1]])
        ref = _reference(slopes, scene, [a], band)
        ref_med = float(ref[1, 0]) if ref is not None else np.nan
        rows.append(
            {
                "scene": scene,
                "multiplier": a,
                "n_sets": int(st["mle"].size),
                "n_images": int(np.median(st["n_images"])),
                "median": med,
                "lo": lo,
                "hi": hi,
                "reference": ref_med,
                "distance": med - ref_med,
            }
        )
    mat = np.full((len(mults), max(1, max(m.size for m in per_a))), np.nan)
    for i, m in enumerate(per_a):
        mat[i, : m.size] = m
    return rows, mat


def measure_cdm_grid(
    files: Mapping[tuple[str, float], Sequence],
    out_npz,
    out_csv,
    fig_stem,
    *,
    run_name: str,
    nfw_scene: str = "nfw",
    tnfw_scene: str | None = "tnfw",
    band=(16, 84),
    source: str | None = None,
    effective_slopes_csv=None,
    reference_scenes: Sequence | None = None,
):
    """Stack MLEs (one per simulated set) for every (scene, multiplier) of ``files``.

    ``files[(scene, a)]``: the profiles files of that scene at multiplier ``a``. Writes the
    MLEs (``out_npz``: multipliers, mles_<scene> (n_a, n_sets) padded with NaN), the
    per-(scene, a) median and ``band`` percentiles (``out_csv``: scene, multiplier,
    n_sets, n_images, median, lo, hi, and with ``effective_slopes_csv`` (rule
    effective_slope) ``reference``, the median effective slope of the sets, and
    ``distance`` = median − reference) and figure 4 with the reference curves. Returns
    the table. ``reference_scenes``: ``(nfw, tnfw)`` of the reference code's sets
    (``cdm.reference_*_scene``), measured alike and drawn as figure 4's second panel.
    """
    import pandas as pd

    slopes = pd.read_csv(effective_slopes_csv) if effective_slopes_csv else None

    from subslope.figures.paper import concentration_grid

    mults = sorted({float(a) for _, a in files})
    ref_nfw, ref_tnfw = tuple(reference_scenes) if reference_scenes else (None, None)
    scenes = [
        s
        for s in dict.fromkeys((nfw_scene, tnfw_scene, ref_nfw, ref_tnfw))
        if s is not None and any(k[0] == s for k in files)
    ]
    rows, arrays = [], {"multipliers": np.asarray(mults)}
    for scene in scenes:
        scene_rows, arrays[f"mles_{scene}"] = _scene_grid(files, scene, mults, band, slopes)
        rows += scene_rows
    table = pd.DataFrame(rows, columns=list(GRID_COLUMNS))
    out_npz = Path(out_npz)
    with atomic_write(out_npz) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays)
    write_text(out_csv, table.to_csv(index=False))
    n_img = int(table["n_images"].median()) if len(table) else 13
    fig = concentration_grid(
        mults,
        arrays[f"mles_{nfw_scene}"],
        arrays.get(f"mles_{tnfw_scene}") if tnfw_scene else None,
        run_name=run_name,
        source=source,
        n_images=n_img,
        percentiles=(band[0], 50, band[1]),
        reference_nfw=_reference(slopes, nfw_scene, mults, band),
        reference_tnfw=_reference(slopes, tnfw_scene, mults, band) if tnfw_scene else None,
        second=None
        if ref_nfw is None
        else {
            "mles_nfw": arrays[f"mles_{ref_nfw}"],
            "mles_tnfw": arrays.get(f"mles_{ref_tnfw}") if ref_tnfw else None,
            "reference_nfw": _reference(slopes, ref_nfw, mults, band),
            "reference_tnfw": _reference(slopes, ref_tnfw, mults, band) if ref_tnfw else None,
        },
    )
    save_figure(fig, fig_stem, run_name=run_name)
    return table


def cdm_band(table, scene: str, multiplier: float = 1.0) -> tuple[float, float, float] | None:
    """``(median, lo, hi)`` of ``scene`` at ``multiplier`` from a cdm_grid table (or None)."""
    if table is None or not len(table):
        return None
    sel = table[(table["scene"] == scene) & np.isclose(table["multiplier"], multiplier)]
    if not len(sel):
        return None
    r = sel.iloc[0]
    return float(r["median"]), float(r["lo"]), float(r["hi"])
