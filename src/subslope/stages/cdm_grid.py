"""Stage ``cdm_grid``: stack MLEs of the simulated CDM sets per concentration
multiplier, their bands, the sets' effective subhalo slopes (a guide to what each
reading could approach, :mod:`subslope.physics.effective_slope`), the matched EPL
controls (what power-law populations of known slope read on the same sets) and figure 4
(rules effective_slope, measure_epl_control and measure_cdm_grid)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from subslope.figures.save import save_figure
from subslope.io.atomic import atomic_write, write_text
from subslope.io.ratio_profiles import read_profiles
from subslope.simulation.resolve import same_multiplier
from subslope.stages.calibrate import set_stacks

__all__ = [
    "GRID_COLUMNS",
    "EFFECTIVE_SLOPE_COLUMNS",
    "set_effective_slopes",
    "effective_slope_table",
    "measure_cdm_grid",
    "cdm_band",
    "CONTROL_COLUMNS",
    "measure_epl_control",
    "control_slope",
    "paired_reading",
    "ABUNDANCE_COLUMNS",
    "measure_abundance",
    "FIGURE4_COLUMNS",
    "figure4_verdicts",
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

#: Columns of ``epl_control.csv``, one row per matched EPL control scene: its grid, its
#: slope, the median and band of its stack MLEs, and the paired shift against the same
#: sets without subhalos (NaN without the subhalo-free re-renders).
CONTROL_COLUMNS = (
    "grid",
    "scene",
    "gamma",
    "n_sets",
    "median",
    "lo",
    "hi",
    "subhalo_free_p50",
    "shift_mean",
    "shift_mean_se",
)

#: Columns of ``abundance.csv``, one row per CDM scene of the abundance series.
ABUNDANCE_COLUMNS = (
    "scene",
    "profile",
    "n_sub_max",
    *CONTROL_COLUMNS[3:],
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
        sel = slopes[(slopes["scene"] == scene) & same_multiplier(slopes["multiplier"], a)]
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


def _controls(control, grid: str) -> list[tuple[float, float]]:
    """``(γ, median)`` of the matched EPL controls of ``grid`` (none without a table)."""
    if control is None:
        return []
    sel = control[control["grid"] == grid]
    return list(zip(sel["gamma"].astype(float), sel["median"].astype(float)))


def _grid_scenes(files, grid_scenes: Sequence[str | None]) -> list[str]:
    """The scenes of ``files``: the grids' scenes first (in order), then any other."""
    others = sorted({k[0] for k in files} - set(grid_scenes))
    return [
        s
        for s in dict.fromkeys((*grid_scenes, *others))
        if s is not None and any(k[0] == s for k in files)
    ]


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
    control_csv=None,
):
    """Stack MLEs (one per simulated set) for every (scene, multiplier) of ``files``.

    ``files[(scene, a)]``: the profiles files of that scene at multiplier ``a``. Writes the
    MLEs (``out_npz``: multipliers, mles_<scene> (n_a, n_sets) padded with NaN), the
    per-(scene, a) median and ``band`` percentiles (``out_csv``: scene, multiplier,
    n_sets, n_images, median, lo, hi, and with ``effective_slopes_csv`` (rule
    effective_slope) ``reference``, the median effective slope of the sets, and
    ``distance`` = median − reference) and figure 4 with the reference curves. Returns
    the table. ``reference_scenes``: ``(nfw, tnfw)`` of the reference code's sets
    (``cdm.reference_*_scene``), measured alike and drawn as figure 4's second panel;
    ``control_csv``: the matched EPL controls (:func:`measure_epl_control`), drawn in
    their grid's panel.
    """
    import pandas as pd

    slopes = pd.read_csv(effective_slopes_csv) if effective_slopes_csv else None
    control = pd.read_csv(control_csv) if control_csv else None

    from subslope.figures.paper import concentration_grid

    mults = sorted({float(a) for _, a in files})
    ref_nfw, ref_tnfw = tuple(reference_scenes) if reference_scenes else (None, None)
    scenes = _grid_scenes(files, (nfw_scene, tnfw_scene, ref_nfw, ref_tnfw))
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
        controls=_controls(control, "field"),
        second=None
        if ref_nfw is None
        else {
            "mles_nfw": arrays[f"mles_{ref_nfw}"],
            "mles_tnfw": arrays.get(f"mles_{ref_tnfw}") if ref_tnfw else None,
            "reference_nfw": _reference(slopes, ref_nfw, mults, band),
            "reference_tnfw": _reference(slopes, ref_tnfw, mults, band) if ref_tnfw else None,
            "controls": _controls(control, "reference"),
        },
    )
    save_figure(fig, fig_stem, run_name=run_name)
    return table


def cdm_band(table, scene: str, multiplier: float = 1.0) -> tuple[float, float, float] | None:
    """``(median, lo, hi)`` of ``scene`` at ``multiplier`` from a cdm_grid table (or None)."""
    if table is None or not len(table):
        return None
    sel = table[(table["scene"] == scene) & same_multiplier(table["multiplier"], multiplier)]
    if not len(sel):
        return None
    r = sel.iloc[0]
    return float(r["median"]), float(r["lo"]), float(r["hi"])


def paired_reading(files: Sequence, removed: Sequence, band=(16, 84)) -> dict:
    """The stack γ_MLE of the sets in the profiles ``files``: ``n_sets``, ``median``,
    ``lo``, ``hi`` (``band`` percentiles) and, with ``removed`` (the same sets re-rendered
    without subhalos; empty: none), ``subhalo_free_p50`` and the paired shift's mean and
    standard error (``shift_mean``, ``shift_mean_se``; NaN without ``removed``)."""
    from subslope.stages.null_tests.visibility import paired_stack_mles

    mle = set_stacks(read_profiles(list(files)))["mle"]
    free = np.full(mle.size, np.nan)
    if removed:
        mle, free = paired_stack_mles(files, removed)
    lo, med, hi = np.percentile(mle, [band[0], 50, band[1]])
    shift = mle - free
    n = int(mle.size)
    return {
        "n_sets": n,
        "median": med,
        "lo": lo,
        "hi": hi,
        "subhalo_free_p50": float(np.median(free)),
        "shift_mean": float(shift.mean()),
        "shift_mean_se": float(shift.std(ddof=1) / np.sqrt(n)) if n > 1 else np.nan,
    }


def measure_epl_control(groups: Sequence, out_csv, *, band=(16, 84)):
    """Rule measure_epl_control: the stack MLEs of every matched EPL control.

    ``groups``: ``(grid, scene, gamma, profiles files, subhalo-free profiles files)``, the
    second list the re-renders without subhalos of the CDM shards whose sets the control
    draws (``common_draws``; empty: no paired shift). Writes ``out_csv``
    (:data:`CONTROL_COLUMNS`) and returns the table."""
    import pandas as pd

    rows = [
        {"grid": grid, "scene": scene, "gamma": float(gamma), **paired_reading(f, r, band)}
        for grid, scene, gamma, f, r in groups
    ]
    table = pd.DataFrame(rows, columns=list(CONTROL_COLUMNS)).sort_values(["grid", "gamma"])
    write_text(out_csv, table.to_csv(index=False))
    return table


def measure_abundance(
    groups: Sequence,
    out_csv,
    fig_stem,
    *,
    z_lens: float,
    field_arcsec: float,
    run_name: str,
    band=(16, 84),
):
    """Rule measure_abundance: the a = 1 reading and paired shift of CDM sets whose
    subhalo count prior is U{0, N_max}, for several N_max (``groups``: ``(scene, profile,
    N_max, profiles files, subhalo-free profiles files)``). Writes ``out_csv``
    (:data:`ABUNDANCE_COLUMNS`) and the figure, marking the N_max whose mean count
    equals what a CDM host at ``z_lens`` projects into the square field of side
    ``field_arcsec`` (:mod:`subslope.physics.abundance`, paltas's Σ_sub prior, ± 1σ).
    Returns the table."""
    import pandas as pd

    from subslope.figures.abundance import abundance_figure
    from subslope.physics.abundance import uniform_count_max

    rows = [
        {"scene": scene, "profile": profile, "n_sub_max": int(n_max), **paired_reading(f, r, band)}
        for scene, profile, n_max, f, r in groups
    ]
    table = pd.DataFrame(rows, columns=list(ABUNDANCE_COLUMNS))
    table = table.sort_values(["profile", "n_sub_max"])
    write_text(out_csv, table.to_csv(index=False))
    expected = uniform_count_max(z_lens, field_arcsec)
    fig = abundance_figure(table, expected=expected, run_name=run_name, source=str(out_csv))
    save_figure(fig, fig_stem, run_name=run_name)
    return table


def control_slope(control, grid: str, reading: float) -> float | None:
    """The slope γ of the matched EPL control of ``grid`` that reads ``reading``: linear
    interpolation of γ in the controls' medians. None when the medians do not rise with γ
    (no reading of that grid maps to a slope) or ``reading`` lies outside their range."""
    if control is None or not len(control):
        return None
    sel = control[control["grid"] == grid].sort_values("gamma")
    med, g = sel["median"].to_numpy(float), sel["gamma"].to_numpy(float)
    if med.size < 2 or not np.all(np.diff(med) > 0):
        return None
    if not med[0] <= reading <= med[-1]:
        return None
    return float(np.interp(reading, med, g))


#: Columns of ``figure4.csv`` (the summary's folder): one row per grid with the numbers
#: that decide its verdict and the verdict itself.
FIGURE4_COLUMNS = (
    "grid",
    "nfw_scene",
    "rises",
    "rise",
    "half_width",
    "shift_rise",
    "shift_rise_se",
    "controls_rise",
    "maps_to",
    "contrast_stack",
    "classifier_auc_stack",
    "verdict",
)

#: A 13-stack Δχ² between a_low and a_high below this holds no usable information.
CONTRAST_FLOOR = 1.0
#: A stack AUC of the direct classifier below this does not separate the two multipliers.
AUC_FLOOR = 0.6


def figure4_verdicts(
    grid_table,
    grids: Mapping[str, tuple],
    *,
    control=None,
    visibility=None,
    contrast=None,
    classifier: Mapping[str, float] | None = None,
    a_pair: tuple[float, float] = (1.0, 8.0),
) -> list[dict]:
    """The verdict on figure 4 of each grid (:data:`FIGURE4_COLUMNS`), from the tables
    that measure it, never from the distance to the effective slope:

    - ``rises``: the NFW medians rise with a (each at least the previous − 0.02) and the
      a_high median exceeds the a_low one by more than the a_low half-width (``rise``,
      ``half_width``); ``shift_rise``: paired shift at a_high − at a_low (± ``_se``);
    - ``controls_rise``: the matched EPL controls' medians rise with γ, and ``maps_to``:
      the control slope of the NFW a_low reading (:func:`control_slope`);
    - ``contrast_stack``: the ideal observer's refitted Δχ² between a_high and a_low in a
      13-stack (the concentration contrast); ``classifier_auc_stack``: the direct
      classifier's held-out stack AUC (``classifier[nfw scene]``, when studied).

    The verdict: "no reading maps to a slope" where the controls do not rise; else "the
    images cannot order a" where even the ideal observer's contrast is below
    :data:`CONTRAST_FLOOR` (the upper bound); else "the estimator reads a" where it
    rises; else "the estimator misses what a direct classifier finds" where the
    classifier's stack AUC reaches :data:`AUC_FLOOR` (the lower bound); else "not
    settled" (the ideal observer separates a_low from a_high, no network shown to);
    "not checked" where a needed table is missing. A classifier at chance bounds nothing
    from above: it never makes "the images cannot order a"."""
    lo_a, hi_a = a_pair
    out = []
    for grid, (nfw, _) in grids.items():
        sel = grid_table[grid_table["scene"] == nfw].sort_values("multiplier")
        med = sel["median"].to_numpy(float)
        at = {float(a): r for a, r in zip(sel["multiplier"], sel.itertuples())}
        row = {"grid": grid, "nfw_scene": nfw, "rises": None, "maps_to": None}
        if lo_a in at and hi_a in at:
            r_lo, r_hi = at[lo_a], at[hi_a]
            row["rise"] = float(r_hi.median - r_lo.median)
            row["half_width"] = float(0.5 * (r_lo.hi - r_lo.lo))
            ordered = bool(np.all(np.diff(med) >= -0.02))
            row["rises"] = ordered and row["rise"] > row["half_width"]
        if visibility is not None and len(visibility):
            vis = visibility[visibility["scene"] == nfw]
            v = {float(a): r for a, r in zip(vis["multiplier"], vis.itertuples())}
            if lo_a in v and hi_a in v:
                row["shift_rise"] = float(v[hi_a].shift_mean - v[lo_a].shift_mean)
                row["shift_rise_se"] = float(np.hypot(v[hi_a].shift_mean_se, v[lo_a].shift_mean_se))
        if control is not None and len(control[control["grid"] == grid]):
            c = control[control["grid"] == grid].sort_values("gamma")["median"].to_numpy(float)
            row["controls_rise"] = bool(c.size > 1 and np.all(np.diff(c) > 0))
            if lo_a in at:
                row["maps_to"] = control_slope(control, grid, float(at[lo_a].median))
        if contrast is not None and len(contrast):
            cs = contrast[(contrast["scene"] == nfw) & np.isclose(contrast["a_high"], hi_a)]
            if len(cs):
                row["contrast_stack"] = float(cs["stack_refit"].iloc[0])
        if classifier and nfw in classifier:
            row["classifier_auc_stack"] = float(classifier[nfw])
        row["verdict"] = _verdict(row)
        out.append(row)
    return out


def _verdict(row: Mapping) -> str:
    if row.get("rises") is None or row.get("controls_rise") is None:
        return "not checked (a table is missing)"
    if not row["controls_rise"]:
        return "no reading maps to a slope (the matched controls do not rise with γ)"
    contrast, auc = row.get("contrast_stack"), row.get("classifier_auc_stack")
    if contrast is not None and contrast < CONTRAST_FLOOR:
        return "the images cannot order a (even an ideal observer who knows the subhalos)"
    if row["rises"]:
        return "the estimator reads a"
    if auc is not None and auc >= AUC_FLOOR:
        return "the estimator misses what a direct classifier finds"
    if contrast is None:
        return "not checked (no concentration contrast)"
    return (
        "not settled: an ideal observer who knows the subhalos tells a = 1 from a = 8, but "
        "neither the estimator nor a direct classifier "
        + ("(none run) " if auc is None else f"(stack AUC {auc:.2f}) ")
        + "is shown to"
    )
