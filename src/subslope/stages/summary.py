"""Stage ``summary``: ``results/summary.md`` and the CSVs beside it (rule write_summary)."""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from datetime import UTC
from pathlib import Path
from typing import Any

import numpy as np

from subslope.io.atomic import write_csv, write_json, write_text
from subslope.stages.calibrate import COVERAGE_COLUMNS
from subslope.stages.cdm_grid import ABUNDANCE_COLUMNS, CONTROL_COLUMNS, cdm_band, control_slope
from subslope.stages.markdown import fmt, md_table
from subslope.stages.null_tests import NULL_COLUMNS
from subslope.stages.null_tests.halo_free import BIAS_COLUMNS, HALO_FREE_COLUMNS, SHEET_COLUMNS
from subslope.stages.null_tests.visibility import VISIBILITY_COLUMNS
from subslope.stages.summary_hst import (
    hst_section,
    leave_one_out_lines,
    meaning_lines,
    reach_lines,
    seeds_lines,
)
from subslope.stats.calibration import coverage_sigma, overconfident

__all__ = ["SUMMARY_SECTIONS", "read_benchmarks", "write_run_record", "write_summary"]


def read_benchmarks(paths_by_stage: Mapping[str, Sequence]) -> list[dict[str, Any]]:
    """Per stage: number of jobs, summed wall time (s), longest job (s) and peak RSS (MB),
    from Snakemake benchmark TSV files (columns ``s``, ``max_rss``). Missing files count 0."""
    import pandas as pd

    rows = []
    for stage, paths in paths_by_stage.items():
        secs, longest, rss, n = 0.0, 0.0, 0.0, 0
        for p in paths:
            if not os.path.exists(p):
                continue
            frame = pd.read_csv(p, sep="\t")
            if not len(frame):
                continue
            s = float(frame["s"].iloc[-1])
            secs, longest, n = secs + s, max(longest, s), n + 1
            mr = pd.to_numeric(frame.get("max_rss", pd.Series([np.nan])), errors="coerce").iloc[-1]
            if np.isfinite(mr):
                rss = max(rss, float(mr))
        rows.append(
            {
                "stage": stage,
                "jobs": n,
                "seconds": round(secs, 2),
                "longest_job_s": round(longest, 2),
                "peak_rss_mb": round(rss, 1),
            }
        )
    return rows


#: Section headings of summary.md, in order.
SUMMARY_SECTIONS = (
    "Configuration",
    "Simulations against the data",
    "HST measurement",
    "Signal budget",
    "CDM predictions (a = 1)",
    "Calibration and coverage",
    "Null tests",
    "Halo-free null test",
    "Estimator trend",
    "Run time per stage",
)


#: Columns of null_tests.csv left out of the summary's table (in the CSV beside it).
NULL_HIDDEN = ("single_mle_p16", "single_mle_p84", "tau_1", "tau_n", "n_per_stack")


def _null_section(folder: Path, null_csv) -> list[str]:
    """The null scenes: does the estimator read γ from anything but the subhalos?"""
    import pandas as pd

    if not null_csv:
        write_csv(folder / "null_tests.csv", [], NULL_COLUMNS)
        return ["Stage `null_tests` not run (or null_tests.scenes empty).\n"]
    table = pd.read_csv(null_csv)
    write_text(folder / "null_tests.csv", table.to_csv(index=False))
    return [
        "Scenes without subhalos (figures/null_tests.png), a report rather than a test: "
        "under the training prior an image without visible perturbations is likelier at "
        "low γ, so even an ideal estimator's profile of it slopes (the pass criterion is "
        "the halo-free null test below):\n",
        md_table(table.to_dict("records"), [c for c in NULL_COLUMNS if c not in NULL_HIDDEN]),
    ]


def _halo_free_section(folder: Path, halo_free_csv, bias_csv) -> list[str]:
    """The halo-free null test's verdict and the bias of γ_MLE by N_sub."""
    import pandas as pd

    if not halo_free_csv:
        write_csv(folder / "halo_free.csv", [], HALO_FREE_COLUMNS)
        write_csv(folder / "nsub_bias.csv", [], BIAS_COLUMNS)
        return ["Rule `halo_free_null` not run (null_tests.halo_free_sets = 0).\n"]
    table = pd.read_csv(halo_free_csv)
    bias = pd.read_csv(bias_csv)
    write_text(folder / "halo_free.csv", table.to_csv(index=False))
    write_text(folder / "nsub_bias.csv", bias.to_csv(index=False))
    tested = table[table["variant"] != "original"]
    passed = tested["passes"].astype(str).str.lower() == "true"
    failed = tested.loc[~passed, "variant"].tolist()
    verdict = (
        "**passes**: with the halos removed the γ_MLE does not follow the label, so γ "
        "reaches the estimator through the halos only."
        if not failed
        else f"**fails** for {', '.join(failed)}: with the halos removed the γ_MLE still "
        "follows the label, so γ reaches the estimator through something other than the "
        "halos (the negative sheets, the placement mask or the macro draw)."
    )
    orig = table[table["variant"] == "original"].iloc[0]
    if abs(orig["rho_stack"]) <= 2.0 / math.sqrt(max(int(orig["n_stacks"]) - 1, 1)):
        verdict += (
            " It is **uninformative** here: the γ_MLE of the original images does not "
            "follow the label either (the estimator reads little or nothing of γ)."
        )
    return [
        "Test images re-rendered from their stored parameters without subhalos and "
        "line-of-sight halos (`sheets_kept`: their negative sheets kept; "
        "`sheets_removed`: removed too), same lens, source, light and noise. Passing "
        "needs |ρ| ≤ 2/√(n − 1) for single images and stacks and a stack slope within "
        f"2 SE of 0. The test {verdict}\n",
        md_table(table.to_dict("records"), list(HALO_FREE_COLUMNS)),
        *_sheet_lines(folder, Path(halo_free_csv).with_name("sheet_channel.csv")),
        "\nBias γ_MLE − γ of the single original images in bins of N_sub:\n",
        md_table(bias.to_dict("records"), list(BIAS_COLUMNS)),
    ]


def _sheet_lines(folder: Path, sheet_csv: Path) -> list[str]:
    """How the kept sheets carry γ (``sheet_channel.csv`` of rule halo_free_null)."""
    import pandas as pd

    if not sheet_csv.is_file():
        return []
    sheet = pd.read_csv(sheet_csv, keep_default_na=False)
    write_text(folder / "sheet_channel.csv", sheet.to_csv(index=False))
    for column in ("rho", "p", "bound"):  # empty cells read as text keep the column text
        sheet[column] = pd.to_numeric(sheet[column], errors="coerce")
    rows = sheet.to_dict("records")
    follow = [r for r in rows if r["against"] == "label" and not r["given"]]
    rest = [r for r in rows if r["given"]]
    if not rest:
        return []
    rest = rest[0]
    inside = str(rest["within"]).lower() == "true"
    text = (
        "\nA sheet is minus its members' mean κ, so it follows γ: "
        + "; ".join(f"{r['quantity']} against the label ρ = {fmt(r['rho'])}" for r in follow)
        + f". With {rest['given']} held fixed, the sheets-kept stack γ_MLE against the "
        f"label has partial ρ = {fmt(rest['rho'])} (bound ±{fmt(rest['bound'])}): "
    )
    text += (
        "nothing of the label is left once the sheets' amplitudes are known, so what the "
        "kept sheets carry is their amplitude, a function of the members' γ that in a "
        "whole image the members' own mean κ cancels.\n"
        if inside
        else "the label still reaches the kept-sheet images beyond the sheets' amplitudes "
        "(their centres, or the placement).\n"
    )
    return [text, md_table(rows, list(SHEET_COLUMNS))]


def _domain_section(domain_csv) -> list[str]:
    """How many HST lenses lie inside the simulated distribution of every statistic."""
    import pandas as pd

    if not domain_csv:
        return ["Stage `domain` not run: nothing shows that the simulations cover the data.\n"]
    table = pd.read_csv(domain_csv, keep_default_na=False)
    inside = table["inside"].astype(str).str.lower() == "true"
    out = table.loc[~inside, ["system", "outside"]].to_dict("records")
    lines = [
        f"{int(inside.sum())} of {len(table)} HST lenses lie inside the simulated 1–99% "
        "range of every statistic (results/check_domain/domain_check.csv, "
        "figures/domain_check.png).\n"
    ]
    if out:
        lines.append(md_table(out, ["system", "outside"]))
    spread = Path(domain_csv).with_name("spread.csv")
    if spread.is_file():
        widths = pd.read_csv(spread).dropna(subset=["width_ratio"])
        if len(widths):
            top = widths.loc[widths["width_ratio"].idxmax()]
            lines.append(
                f"The simulated 1–99% range is at most {top['width_ratio']:.1f}× the HST "
                f"range ({top['statistic']}; results/check_domain/spread.csv).\n"
            )
    return lines


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
                cdm[(cdm["scene"] == scene) & np.isclose(cdm["multiplier"], 1.0)]["n_sets"].iloc[0]
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


def _calibration_section(folder: Path, calibration_csv) -> list[str]:
    import pandas as pd

    if not calibration_csv:
        write_csv(folder / "coverage.csv", [], COVERAGE_COLUMNS)
        return ["Stage `calibrate` not run.\n"]
    table = pd.read_csv(calibration_csv)
    write_text(folder / "coverage.csv", table.to_csv(index=False))
    if "coverage_sigma" not in table:  # a table of an older run
        level = table["level"] if "level" in table else 0.68
        table["coverage_sigma"] = coverage_sigma(
            level, table["n_stacks"] - table["n_heldout"], table["n_heldout"]
        )
        table["overconfident"] = overconfident(table["coverage"], table["coverage_sigma"], level)
    flagged = [int(n) for n in table.loc[table["overconfident"].astype(bool), "n_images"]]
    warning = (
        f"**Over-confident at N = {', '.join(map(str, flagged))}**: held-out coverage more "
        "than 2σ below the level.\n"
        if flagged
        else "No N has held-out coverage more than 2σ below the level.\n"
    )
    return [
        "Held-out coverage of the 68% intervals with the calibrated threshold τ_N "
        "(and with Wilks' χ²₁ threshold). `coverage_err` is the binomial error of the "
        "held-out stacks alone; `coverage_sigma` adds the scatter of the threshold set by "
        "the calibration stacks, and is the σ of the 2σ test:\n",
        md_table(
            table.to_dict("records"),
            [
                "n_images",
                "n_stacks",
                "tau",
                "tau_exact",
                "coverage",
                "coverage_err",
                "coverage_sigma",
                "coverage_wilks",
                "n_heldout",
                "overconfident",
            ],
        ),
        warning,
    ]


def _response_lines(folder: Path, signal_csv, visibility_csv, halo_free_csv, run_name) -> list[str]:
    """The estimator's response against the signal (``response.csv``, figures/response.*)."""
    import pandas as pd

    from subslope.figures.save import save_figure
    from subslope.figures.signal import response_figure
    from subslope.stages.signal_budget import RESPONSE_COLUMNS, response_table

    table = response_table(signal_csv, visibility_csv, halo_free_csv) if signal_csv else None
    if table is None:
        table = pd.DataFrame(columns=list(RESPONSE_COLUMNS))
    write_csv(folder / "response.csv", table.to_dict("records"), RESPONSE_COLUMNS)
    fig = response_figure(table, run_name=run_name, source="results/response.csv")
    save_figure(fig, folder / "figures" / "response", run_name=run_name)
    if not len(table):
        return []
    return [
        "\nThe estimator's response against that signal (`shift`: how far removing the "
        "halos moves the stack γ_MLE; CDM sets paired with their subhalo-free re-renders, "
        "EPL test sets as the difference of medians against their halo-free re-renders; "
        "figures/response.png). The Δχ² bounds whether subhalos of known positions and "
        "masses could be detected, not what can be learnt about their concentration; the "
        "concentration contrast and the classifier study (docs/inference.md) bound that:\n",
        md_table(table.to_dict("records"), list(RESPONSE_COLUMNS)),
    ]


def _signal_section(signal_csv) -> list[str]:
    """The signal budget of every scene (results/signal_budget/signal_budget.csv)."""
    import pandas as pd

    if not signal_csv:
        return ["Stage `signal_budget` not run.\n"]
    table = pd.read_csv(signal_csv)
    table["multiplier"] = table["multiplier"].fillna("")
    return [
        "The ideal observer's Δχ² of each scene's subhalos per image (16/50/84%), inside "
        "the estimator's mask, with the smooth model fixed and after a full (Gauss-Newton) "
        "refit of every lens, lens-light, sky and source-position parameter (source "
        "morphology fixed, so both are upper bounds; `linear_p50`: the median after the "
        "first, linearised step alone); `stack_refit` is the refitted Δχ² of a stack "
        "(the stack size × the median). Δχ² ≈ 1 is invisible, ≳ 25 an individual "
        "detection (figures/signal_budget.png):\n",
        md_table(table.to_dict("records"), list(table.columns)),
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


def _contrast_lines(folder: Path, contrast_csv) -> list[str]:
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


def _trend_section(folder: Path, trend: Mapping[str, float] | None) -> list[str]:
    if not trend:
        write_csv(folder / "trend.csv", [], ["rho", "p_value", "n"])
        return ["Not computed (calibration or figures stage off).\n"]
    write_csv(folder / "trend.csv", [dict(trend)])
    return [
        f"Spearman ρ between the true γ and the stack γ_MLE of the EPL test sets: "
        f"ρ = {fmt(trend.get('rho'))} (p = {float(trend.get('p_value', float('nan'))):.3g}, "
        f"{int(trend.get('n', 0))} sets).\n"
    ]


def _runtime_section(folder: Path, benchmarks: Mapping[str, Sequence] | None) -> list[str]:
    columns = ["stage", "jobs", "seconds", "longest_job_s", "peak_rss_mb"]
    rows = read_benchmarks(benchmarks or {})
    write_csv(folder / "stage_runtime.csv", rows, columns)
    return [
        "Summed job wall time per stage (Snakemake benchmark files; jobs run in parallel, so the "
        "sum "
        "exceeds the wall time of the run):\n",
        md_table(rows, columns),
    ]


def write_summary(
    out_md,
    *,
    run_name: str,
    config_hash: str,
    config_file: str = "",
    hst_csv=None,
    loo_csv=None,
    cdm_csv=None,
    calibration_csv=None,
    domain_csv=None,
    null_csv=None,
    halo_free_csv=None,
    bias_csv=None,
    visibility_csv=None,
    signal_csv=None,
    seeds_csv=None,
    trend: Mapping[str, float] | None = None,
    benchmarks: Mapping[str, Sequence] | None = None,
    nfw_scene: str = "nfw",
    tnfw_scene: str | None = "tnfw",
    reference_scenes: Sequence[str | None] | None = None,
    control_csv=None,
    contrast_csv=None,
    abundance_csv=None,
    classifier_json: Sequence | None = None,
    highlight: Sequence[str] = (),
) -> Path:
    """``summary.md`` and, beside it, ``hst_result.csv``, ``cdm_prediction.csv``,
    ``coverage.csv``, ``null_tests.csv``, ``halo_free.csv``, ``nsub_bias.csv``,
    ``cdm_visibility.csv``, ``trend.csv`` and ``stage_runtime.csv`` (``signal_csv``: the
    signal-budget table, shown as it is; ``seeds_csv``: ``subslope seeds``'s table of the
    trainings, if any). Any input may be
    None (its stage was off): the section then says so."""
    out_md = Path(out_md)
    folder = out_md.parent
    folder.mkdir(parents=True, exist_ok=True)
    items = [f"- run_name: `{run_name}`", f"- config hash: `{config_hash}`"]
    if config_file:
        items.append(f"- config file(s): `{config_file}`")
    sections = [
        ["\n".join(items) + "\n"],
        _domain_section(domain_csv),
        hst_section(folder, hst_csv, null_csv)
        + leave_one_out_lines(loo_csv, highlight)
        + seeds_lines(seeds_csv)
        + meaning_lines(folder / "hst_result.csv", null_csv, seeds_csv)
        + reach_lines(folder / "hst_result.csv", signal_csv, (nfw_scene, tnfw_scene)),
        _signal_section(signal_csv)
        + _response_lines(folder, signal_csv, visibility_csv, halo_free_csv, run_name)
        + _contrast_lines(folder, contrast_csv),
        _cdm_section(
            folder, cdm_csv, (nfw_scene, tnfw_scene, *(reference_scenes or ())), visibility_csv
        )
        + _control_lines(folder, cdm_csv, control_csv, (nfw_scene, *(reference_scenes or ())))
        + _abundance_lines(folder, abundance_csv)
        + _figure4_lines(
            folder,
            cdm_csv,
            {
                "field": (nfw_scene, tnfw_scene),
                **({"reference": tuple(reference_scenes)} if reference_scenes else {}),
            },
            control_csv,
            visibility_csv,
            contrast_csv,
            classifier_json,
        ),
        _calibration_section(folder, calibration_csv),
        _null_section(folder, null_csv),
        _halo_free_section(folder, halo_free_csv, bias_csv),
        _trend_section(folder, trend),
        _runtime_section(folder, benchmarks),
    ]
    lines = [f"# subslope campaign summary: `{run_name}`\n"]
    for title, body in zip(SUMMARY_SECTIONS, sections):
        lines.append(f"## {title}\n")
        lines.extend(body)
    return write_text(out_md, "\n".join(lines))


def write_run_record(
    out_json, *, run_name: str, config_hash: str, config_files: Sequence[str]
) -> Path:
    """``run.json`` beside the summary: what made the campaign (run name, config files and
    hash, package version), on which machine
    (:func:`subslope.devices.machine_description`) and when (UTC). It records the
    environment, not a result: ``subslope compare-runs`` skips it, and
    ``subslope results-page`` quotes it."""
    from datetime import datetime

    from subslope._version import __version__
    from subslope.devices import machine_description

    record = {
        "run_name": run_name,
        "config_hash": config_hash,
        "config_files": list(config_files),
        "subslope": __version__,
        "finished_utc": datetime.now(UTC).strftime("%Y-%m-%d %H:%M"),
        "machine": machine_description(),
    }
    out = Path(out_json)
    write_json(out, record)
    return out
