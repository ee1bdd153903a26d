"""Stage ``cdm_grid``: stack MLEs of the simulated CDM sets per concentration
multiplier, their bands and figure 4 (rule measure_cdm_grid)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from subslope.figures.save import save_figure
from subslope.io.atomic import atomic_write, write_text
from subslope.io.ratio_profiles import read_profiles
from subslope.stages.calibrate import set_stacks

__all__ = ["measure_cdm_grid", "cdm_band"]


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
):
    """Stack MLEs (one per simulated set) for every (scene, multiplier) of ``files``.

    ``files[(scene, a)]``: the profiles files of that scene at multiplier ``a``. Writes the
    MLEs (``out_npz``: multipliers, mles_<scene> (n_a, n_sets) padded with NaN), the
    per-(scene, a) median and ``band`` percentiles (``out_csv``: scene, multiplier,
    n_sets, n_images, median, lo, hi) and figure 4. Returns the table.
    """
    import pandas as pd

    from subslope.figures.paper import concentration_grid

    mults = sorted({float(a) for _, a in files})
    scenes = [s for s in (nfw_scene, tnfw_scene) if s is not None and any(k[0] == s for k in files)]
    rows, arrays = [], {"multipliers": np.asarray(mults)}
    for scene in scenes:
        per_a = []
        for a in mults:
            paths = files.get((scene, a))
            if not paths:
                per_a.append(np.array([]))
                continue
            st = set_stacks(read_profiles(paths))
            per_a.append(st["mle"])
            lo, med, hi = np.percentile(st["mle"], [band[0], 50, band[1]])
            rows.append(
                {
                    "scene": scene,
                    "multiplier": a,
                    "n_sets": int(st["mle"].size),
                    "n_images": int(np.median(st["n_images"])),
                    "median": med,
                    "lo": lo,
                    "hi": hi,
                }
            )
        width = max(1, max(m.size for m in per_a))
        mat = np.full((len(mults), width), np.nan)
        for i, m in enumerate(per_a):
            mat[i, : m.size] = m
        arrays[f"mles_{scene}"] = mat
    table = pd.DataFrame(
        rows, columns=["scene", "multiplier", "n_sets", "n_images", "median", "lo", "hi"]
    )
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
