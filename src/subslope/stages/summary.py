"""Stage ``summary``: ``results/summary.md`` and the CSVs beside it (rule write_summary)."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from datetime import UTC
from pathlib import Path
from typing import Any

import numpy as np

from subslope.io.atomic import write_csv, write_json, write_text
from subslope.stages.calibrate import COVERAGE_COLUMNS
from subslope.stages.markdown import fmt, md_table
from subslope.stages.null_tests import NULL_COLUMNS
from subslope.stages.null_tests.halo_free import (
    BIAS_COLUMNS,
    HALO_FREE_COLUMNS,
    SHEET_COLUMNS,
    halo_free_verdict,
)
from subslope.stages.summary_cdm import cdm_lines, contrast_lines
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
    v = halo_free_verdict(table.to_dict("records"))
    if v is None:
        verdict = "is **not checked**: no sheets_removed variant in the table."
    elif v["passes"]:
        verdict = (
            "**passes**: with the halos and their sheets removed the γ_MLE does not follow "
            "the label, so γ reaches the estimator through the halos."
        )
    else:
        verdict = (
            "**fails**: with the halos and their sheets removed the γ_MLE still follows the "
            "label, so γ reaches the estimator through something other than the halos (the "
            "placement mask or the macro draw)."
        )
    if v is not None and v["sheets_carry"]:
        verdict += (
            " With the sheets kept the γ_MLE still follows the label: the halos' negative "
            "sheets, whose amplitude is a function of the members' γ, carry part of it (the "
            "sheet-channel table below)."
        )
    if v is not None and v["uninformative"]:
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
        + contrast_lines(folder, contrast_csv),
        cdm_lines(
            folder,
            cdm_csv,
            {
                "field": (nfw_scene, tnfw_scene),
                **({"reference": tuple(reference_scenes)} if reference_scenes else {}),
            },
            cdm_scenes=(nfw_scene, tnfw_scene, *(reference_scenes or ())),
            control_csv=control_csv,
            abundance_csv=abundance_csv,
            visibility_csv=visibility_csv,
            contrast_csv=contrast_csv,
            classifier_json=classifier_json,
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
