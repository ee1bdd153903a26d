"""The CDM part of ``summary.md``: the a = 1 prediction, every multiplier against the
sets' effective slope, whether the subhalos reach the estimator, the matched EPL
controls, the abundance series, the concentration contrast and figure 4's verdict per
grid."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from subslope.io.atomic import write_csv, write_text
from subslope.simulation.resolve import same_multiplier
from subslope.stages.cdm_grid import ABUNDANCE_COLUMNS, CONTROL_COLUMNS, cdm_band, control_slope
from subslope.stages.markdown import md_table
from subslope.stages.null_tests.visibility import VISIBILITY_COLUMNS

__all__ = ["CONTRAST_SUMMARY_COLUMNS", "cdm_lines", "contrast_lines", "contrast_summary"]


def cdm_lines(
    folder: Path,
    cdm_csv,
    grids: Mapping[str, Sequence[str | None]],
    *,
    cdm_scenes: Sequence[str | None],
    control_csv=None,
    abundance_csv=None,
    visibility_csv=None,
    contrast_csv=None,
    classifier_json: Sequence | None = None,
) -> list[str]:
    """The summary's CDM section; writes ``cdm_prediction.csv``, ``cdm_visibility.csv``,
    ``epl_control.csv``, ``abundance.csv`` and ``figure4.csv`` into ``folder``.
    ``grids``: ``{grid: (nfw_scene, tnfw_scene)}`` (:func:`subslope.config.cdm_grids`)."""
    nfw_scenes = [pair[0] for pair in grids.values()]
    return (
        _cdm_section(folder, cdm_csv, cdm_scenes, visibility_csv)
        + _control_lines(folder, cdm_csv, control_csv, nfw_scenes)
        + _abundance_lines(folder, abundance_csv)
        + _figure4_lines(
            folder, cdm_csv, grids, control_csv, visibility_csv, contrast_csv, classifier_json
        )
    )


def _cdm_section(
    folder: Path, cdm_csv, scenes: Sequence[str | None], visibility_csv=None
) -> list[str]:
    import pandas as pd

    columns = ["scene", "median", "p16", "p84", "n_sets"]
    if not cdm_csv:
        write_csv(folder / "cdm_prediction.csv", [], columns)
        _visibility_lines(folder, None)  # its header-only CSV: no a = 1 sets to check
        return ["Stage `cdm_grid` not run.\n"]
    cdm = pd.read_csv(cdm_csv)
    rows = []
    for scene in scenes:
        if scene is None:
            continue
        b = cdm_band(cdm, scene)
        if b is not None:
            n_sets = int(
                cdm[(cdm["scene"] == scene) & same_multiplier(cdm["multiplier"], 1.0)][
                    "n_sets"
                ].iloc[0]
            )
            rows.append(
                {"scene": scene, "median": b[0], "p16": b[1], "p84": b[2], "n_sets": n_sets}
            )
    write_csv(folder / "cdm_prediction.csv", rows, columns)
    return [
        "Median and 16–84% range of the stack γ_MLE of simulated CDM sets at a = 1:\n",
        md_table(rows, columns) if rows else "no a = 1 sets\n",
        *_reference_lines(cdm),
        *_visibility_lines(folder, visibility_csv),
    ]


def _figure4_lines(
    folder: Path, cdm_csv, grids, control_csv, visibility_csv, contrast_csv, classifier_json
) -> list[str]:
    """The verdict on figure 4 of each grid (``figure4.csv``,
    :func:`subslope.stages.cdm_grid.figure4_verdicts`) and the classifier records."""
    import json

    import pandas as pd

    from subslope.stages.cdm_grid import FIGURE4_COLUMNS, figure4_verdicts

    if not cdm_csv:
        write_csv(folder / "figure4.csv", [], FIGURE4_COLUMNS)
        return []
    records = [json.loads(Path(p).read_text(encoding="utf-8")) for p in classifier_json or ()]
    rows = figure4_verdicts(
        pd.read_csv(cdm_csv),
        grids,
        control=pd.read_csv(control_csv) if control_csv else None,
        visibility=pd.read_csv(visibility_csv) if visibility_csv else None,
        contrast=contrast_summary(contrast_csv) if contrast_csv else None,
        classifier={r["scene"]: r["auc_stack"] for r in records},
    )
    write_csv(folder / "figure4.csv", rows, FIGURE4_COLUMNS)
    lines = ["\nWhat figure 4 says, grid by grid (figure4.csv):\n"]
    lines += [f"- {r['grid']} ({r['nfw_scene']}): {r['verdict']}.\n" for r in rows]
    if records:
        columns = [
            "scene",
            "a_low",
            "a_high",
            "n_per_class",
            "auc_image",
            "info_nats_image",
            "auc_stack",
            "heldout_stacks",
        ]
        lines += [
            "\nThe direct classifier of a_low against a_high "
            "(studies/concentration_classifier.py, held-out sets):\n",
            md_table(records, columns),
        ]
    return lines


def _abundance_lines(folder: Path, abundance_csv) -> list[str]:
    """The a = 1 reading against the assumed abundance (``abundance.csv``) and the count
    a CDM host projects into the field."""
    import pandas as pd

    from subslope.physics.abundance import PALTAS_SIGMA_SUB, uniform_count_max

    if not abundance_csv:
        write_csv(folder / "abundance.csv", [], ABUNDANCE_COLUMNS)
        return []
    table = pd.read_csv(abundance_csv)
    write_text(folder / "abundance.csv", table.to_csv(index=False))
    lo, mid, hi = uniform_count_max(0.2, 4.0)
    return [
        "\nThe a = 1 reading against the assumed abundance: the same sets with N_sub ~ "
        "U{0, N_max}, where the source lands (figures/abundance.png):\n",
        md_table(table.to_dict("records"), list(ABUNDANCE_COLUMNS)),
        f"\nA CDM host at z = 0.2 projects {mid / 2:.0f} subhalos of 10⁷–10¹⁰ M☉ into the "
        f'4" field ({lo / 2:.0f}–{hi / 2:.0f}; Σ_sub = {PALTAS_SIGMA_SUB[0]:g} ± '
        f"{PALTAS_SIGMA_SUB[1]:g} kpc⁻² at 10¹⁰ M☉, the paltas training prior, "
        "subslope.physics.abundance): a prior of mean count that size is U{0, "
        f"{mid:.0f}}}.\n",
    ]


def _control_lines(folder: Path, cdm_csv, control_csv, nfw_scenes) -> list[str]:
    """The matched EPL controls (``epl_control.csv``) and, per grid, the slope of the
    control that its NFW a = 1 reading matches."""
    import pandas as pd

    if not control_csv:
        write_csv(folder / "epl_control.csv", [], CONTROL_COLUMNS)
        return [
            "\nMatched EPL controls: none configured (cdm.field_controls, reference_controls).\n"
        ]
    control = pd.read_csv(control_csv)
    write_text(folder / "epl_control.csv", control.to_csv(index=False))
    cdm = pd.read_csv(cdm_csv) if cdm_csv else None
    lines = [
        "\nMatched EPL controls: EPL subhalos of one slope γ with each grid's counts, masses "
        "and placement, on the same sets (median and 16–84% of the stack γ_MLE; `shift`: "
        "against the same sets without subhalos):\n",
        md_table(control.to_dict("records"), list(CONTROL_COLUMNS)),
    ]
    for grid, nfw in zip(("field", "reference"), nfw_scenes):
        sel = control[control["grid"] == grid].sort_values("gamma")
        if nfw is None or not len(sel):
            continue
        med = sel["median"].to_numpy(float)
        if not np.all(np.diff(med) > 0):
            lines.append(
                f"- {grid}: the controls' medians do not rise with γ "
                f"({', '.join(f'{v:.2f}' for v in med)} at γ = "
                f"{', '.join(f'{g:g}' for g in sel['gamma'])}): no reading of this grid maps "
                "to a slope.\n"
            )
            continue
        band = cdm_band(cdm, nfw)
        if band is None:
            continue
        g = control_slope(control, grid, band[0])
        where = (
            f"the reading of an EPL population of γ ≈ {g:.2f}"
            if g is not None
            else "outside the controls' range "
            f"[{med[0]:.2f}, {med[-1]:.2f}] (γ {sel['gamma'].min():g}–{sel['gamma'].max():g})"
        )
        lines.append(f"- {grid}: {nfw} at a = 1 reads {band[0]:.2f}, {where}.\n")
    return lines


def _reference_lines(cdm) -> list[str]:
    """Every multiplier's reading against the sets' effective slope (figure 4's curves)."""
    if "reference" not in cdm or not np.isfinite(cdm["reference"]).any():
        return []
    columns = ["scene", "multiplier", "median", "lo", "hi", "reference", "distance"]
    far = cdm.loc[cdm["distance"].abs().idxmax()]
    return [
        "\nAt every multiplier, the stack γ_MLE (median, 16–84%) against `reference`, the "
        "median over the sets of their subhalos' effective slope (the slope of each "
        'subhalo\'s deflection between 0.04" and 0.4", weighted by its squared '
        "deflection; docs/physics.md), and `distance` = median − reference:\n",
        md_table(cdm[columns].to_dict("records"), columns),
        f"\nThe readings lie {cdm['distance'].abs().min():.2f}–{cdm['distance'].abs().max():.2f} "
        f"from the reference (farthest: {far['scene']} a = {float(far['multiplier']):g}, "
        f"{float(far['distance']):+.2f}).\n",
    ]


def _visibility_lines(folder: Path, visibility_csv) -> list[str]:
    """Do the a = 1 subhalos reach the estimator (``cdm_visibility.csv``)?"""
    import pandas as pd

    if not visibility_csv:
        write_csv(folder / "cdm_visibility.csv", [], VISIBILITY_COLUMNS)
        return ["\nRule `cdm_visibility` not run (null_tests.cdm_visibility: false).\n"]
    table = pd.read_csv(visibility_csv)
    write_text(folder / "cdm_visibility.csv", table.to_csv(index=False))
    visible = table["visible"].astype(str).str.lower() == "true"
    if "multiplier" not in table:
        table.insert(1, "multiplier", 1.0)
    label = [f"{r.scene} a = {float(r.multiplier):g}" for r in table.itertuples()]
    table["label"] = label
    seen = [
        f"{r.label} by {r.shift_mean:+.3f} ± {r.shift_mean_se:.3f} on average (Wilcoxon "
        f"p = {r.wilcoxon_p:.2g}; the same sets without subhalos: median "
        f"{r.subhalo_free_mle_p50:.2f})"
        for r in table[visible].itertuples()
    ]
    blind = table.loc[~visible, "label"].tolist()
    verdict = (
        f"Removing the subhalos moves the stack γ_MLE of {'; of '.join(seen)}. " if seen else ""
    )
    if blind:
        verdict += (
            f"**The subhalos of {', '.join(blind)} are not seen by the estimator**: removing "
            "them leaves the stack γ_MLE where it was (Wilcoxon p ≥ 0.05), so there the grid "
            "is the estimator's reading of subhalo-free images, not a measurement of the "
            "subhalos' slope, and it cannot order NFW against tNFW or concentrations."
        )
    return [
        "\nThe same sets re-rendered without their subhalos (line-of-sight halos, "
        "lens, source, light and noise seeds as stored; `shift`: the stack γ_MLE with the "
        f"subhalos minus without, per set). {verdict}\n",
        md_table(table.to_dict("records"), list(VISIBILITY_COLUMNS)),
    ]


#: Columns of ``concentration_contrast.csv`` in the summary: per scene, the median
#: Δχ² per image between its a_high and a_low images, fixed and refitted, and of a stack.
CONTRAST_SUMMARY_COLUMNS = (
    "scene",
    "a_low",
    "a_high",
    "n_images",
    "fixed_p50",
    "refit_p16",
    "refit_p50",
    "refit_p84",
    "stack_refit",
)


def contrast_summary(contrast_csv, stack_size: int = 13):
    """One row (:data:`CONTRAST_SUMMARY_COLUMNS`) per scene of the concentration contrast:
    ``stack_refit`` = ``stack_size`` × the median refitted Δχ² per image."""
    import pandas as pd

    data = pd.read_csv(contrast_csv)
    rows = []
    for (scene, lo, hi), g in data.groupby(["scene", "a_low", "a_high"], sort=False):
        refit = g["dchi2_refit"].to_numpy(float)
        rows.append(
            {
                "scene": scene,
                "a_low": float(lo),
                "a_high": float(hi),
                "n_images": len(g),
                "fixed_p50": float(np.median(g["dchi2_fixed"])),
                "refit_p16": float(np.percentile(refit, 16)),
                "refit_p50": float(np.median(refit)),
                "refit_p84": float(np.percentile(refit, 84)),
                "stack_refit": float(stack_size * np.median(refit)),
            }
        )
    return pd.DataFrame(rows, columns=list(CONTRAST_SUMMARY_COLUMNS))


def contrast_lines(folder: Path, contrast_csv) -> list[str]:
    """How much an ideal observer could tell the two multipliers apart (rule
    concentration_contrast), written to ``concentration_contrast.csv``."""
    if not contrast_csv:
        write_csv(folder / "concentration_contrast.csv", [], CONTRAST_SUMMARY_COLUMNS)
        return []
    table = contrast_summary(contrast_csv)
    write_text(folder / "concentration_contrast.csv", table.to_csv(index=False))
    return [
        "\nHow much the images can say about the concentration, from above: the Δχ² between "
        "each image at a_high and the same draw at a_low (subhalo positions and masses "
        "known, the smooth model refitted; `stack_refit`: 13 × the median). An observer "
        "who must also infer the subhalos sees less:\n",
        md_table(table.to_dict("records"), list(CONTRAST_SUMMARY_COLUMNS)),
    ]
