"""``docs/results.md``: the page of a finished campaign's results, generated from its
``results/`` folder (``subslope results-page results/``), never edited by hand.

The page states what made the numbers (command, config, machine, date: ``run.json``),
gives the verdict of each part in one sentence computed from the CSVs beside
``summary.md`` (in-distribution reading, coverage, halo-free null test, CDM visibility,
HST result against the subhalo-free null stacks, domain check), says what each part can
and cannot be taken to mean, and then carries the summary's tables unchanged.
"""

from __future__ import annotations

import csv
import json
import math
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from subslope.io.atomic import write_text

__all__ = [
    "ResultsPageError",
    "SUMMARY_TABLES",
    "results_page",
    "verdicts",
    "write_results_page",
]


class ResultsPageError(ValueError):
    """The results folder is not that of a finished campaign."""


#: Tables ``write_summary`` writes beside ``summary.md`` (header-only where a stage is
#: off) that the verdicts read: a finished campaign's folder holds every one.
SUMMARY_TABLES = (
    "trend.csv",
    "coverage.csv",
    "halo_free.csv",
    "cdm_prediction.csv",
    "cdm_visibility.csv",
    "figure4.csv",
    "hst_result.csv",
    "null_tests.csv",
)


class _Tables:
    """The CSVs of a results folder, read once each; remembers every table it could not
    read (a summary table missing, or any table cut short) for the page to name."""

    def __init__(self, results: Path):
        self.results = results
        self.unread: dict[str, str] = {}
        self._cache: dict[str, list[dict[str, str]]] = {}

    def rows(self, name: str) -> list[dict[str, str]]:
        if name not in self._cache:
            self._cache[name] = self._read(name)
        return self._cache[name]

    def read(self, name: str) -> bool:
        """Whether ``name`` was read whole (after :meth:`rows`)."""
        self.rows(name)
        return name not in self.unread

    def _read(self, name: str) -> list[dict[str, str]]:
        path = self.results / name
        if not path.is_file():
            if name in SUMMARY_TABLES:
                self.unread[name] = "missing"
            return []
        with path.open(encoding="utf-8", newline="") as fh:
            reader = csv.DictReader(fh)
            rows = list(reader)
        width = len(reader.fieldnames or ())
        short = [k for k, r in enumerate(rows, 2) if None in r.values() or None in r]
        if not width or short:
            where = f"line {short[0]} has not {width} fields" if short else "no header"
            self.unread[name] = f"unreadable: {where}"
            return []
        return rows


def _num(value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _true(value: Any) -> bool:
    return str(value).strip().lower() == "true"


def _in_distribution(t: _Tables) -> list[str]:
    out = []
    trend = t.rows("trend.csv")
    if trend and math.isfinite(_num(trend[0]["rho"])):
        out.append(
            f"On its own EPL test sets the estimator reads γ: Spearman ρ = "
            f"{_num(trend[0]['rho']):.2f} between the true γ and the stack γ_MLE "
            f"({trend[0]['n']} sets)."
        )
    coverage = t.rows("coverage.csv")
    if not t.read("coverage.csv"):
        out.append("Held-out coverage: not checked (coverage.csv could not be read).")
    elif coverage:
        bad = [r["n_images"] for r in coverage if _true(r["overconfident"])]
        ns = ", ".join(r["n_images"] for r in coverage)
        out.append(
            f"Held-out coverage of the 68% intervals is within 2σ of the level at every N ({ns})."
            if not bad
            else f"Held-out coverage is more than 2σ below 68% at N = {', '.join(bad)}: "
            "the intervals of those stack sizes are too narrow."
        )
    from subslope.stages.null_tests.halo_free import halo_free_verdict

    verdict = halo_free_verdict(t.rows("halo_free.csv"))
    if not t.read("halo_free.csv"):
        out.append("The halo-free null test: not checked (halo_free.csv could not be read).")
    elif verdict is not None:
        out.append(
            "With subhalos and line-of-sight halos removed the reading no longer follows "
            "the label (halo-free null test passes): γ reaches the estimator through the "
            "halos."
            if verdict["passes"]
            else "The halo-free null test FAILS: with the halos removed the reading still "
            "follows the label, so the estimator reads γ from something else."
        )
        if verdict["sheets_carry"]:
            out.append(
                "With the halos' negative sheets kept the reading still follows the label "
                f"(stack ρ = {verdict['kept_rho_stack']:.2f}): the sheets' amplitude, a "
                "function of the members' γ, carries part of it (the summary's sheet-channel "
                "table); this is what the halos carry, not a failure of the test."
            )
    return out


def _cdm(t: _Tables) -> list[str]:
    rows = t.rows("cdm_visibility.csv")
    if not rows:
        return []

    def label(r):
        return f"{r['scene']} a = {_num(r.get('multiplier') or 1.0):g}"

    seen = [label(r) for r in rows if _true(r["visible"])]
    unseen = [label(r) for r in rows if not _true(r["visible"])]
    out = []
    if unseen:
        out.append(
            f"The CDM subhalos of {', '.join(unseen)} do not move the estimator (paired "
            "shift against the same sets without subhalos consistent with 0): there figure "
            "4 shows the estimator's reading of subhalo-free images, not a prediction of "
            "the subhalos' slope."
        )
    if seen:
        moved = "; ".join(
            f"{label(r)} {_num(r['shift_mean']):+.3f} ± {_num(r['shift_mean_se']):.3f}"
            for r in rows
            if _true(r["visible"])
        )
        out.append(
            f"The CDM subhalos move the estimator's stack γ_MLE (paired shift against the "
            f"same sets without them, Wilcoxon p < 0.05): {moved}. The signal these sets "
            "hold (results/response.csv) bounds detection, not what the images can say "
            "about the concentration: the concentration contrast does."
        )
    return out


def _figure4(t: _Tables) -> list[str]:
    """Figure 4's verdict per grid (``figure4.csv``, written by the summary from
    :func:`subslope.stages.cdm_grid.figure4_verdicts`)."""
    rows = t.rows("figure4.csv")
    if not t.read("figure4.csv"):
        return ["Figure 4: not checked (figure4.csv could not be read)."]
    if not rows:
        return []
    parts = "; ".join(f"{r['grid']} grid ({r['nfw_scene']}): {r['verdict']}" for r in rows)
    return [f"Figure 4, from its matched controls and the concentration contrast: {parts}."]


def _reference(t: _Tables) -> list[str]:
    rows = [
        r
        for r in t.rows("measure_cdm_grid/cdm_grid.csv")
        if r.get("reference") and math.isfinite(_num(r["reference"]))
    ]
    if not rows:
        return []
    parts = "; ".join(
        f"{r['scene']} a = {_num(r['multiplier']):g} {_num(r['median']):.2f} against "
        f"{_num(r['reference']):.2f}"
        for r in rows
    )
    return [
        "Figure 4's readings against the effective slope of the sets' subhalos (a guide, "
        f"not what an estimator trained on EPL populations must read): {parts}."
    ]


def _seeds(t: _Tables) -> list[str]:
    rows = t.rows("seeds/seeds.csv")
    if len(rows) < 2:
        return []
    g = [_num(r["hst_gamma_mle"]) for r in rows]
    n_open = sum(r["hst_open"] != "no" for r in rows)
    return [
        f"Over {len(rows)} trainings of the estimator (`subslope seeds`) the combined HST "
        f"γ_MLE spans {min(g):.2f}–{max(g):.2f}; {n_open} of {len(rows)} intervals are open "
        "at a prior edge."
    ]


def _signal(t: _Tables) -> list[str]:
    rows = [r for r in t.rows("signal_budget/signal_budget.csv") if _num(r["fixed_p50"]) > 0]
    if not rows:
        return []
    parts = [
        f"{r['scene']}{' a = ' + format(_num(r['multiplier']), 'g') if r['multiplier'] else ''}"
        f" {_num(r['refit_p50']):.3g} ({_num(r['fixed_p50']):.3g} with the smooth model fixed)"
        for r in rows
    ]
    return [
        "The ideal observer's Δχ² of the subhalos per image, median after a refit "
        f"of the smooth model: {'; '.join(parts)} (≈ 1 invisible, ≳ 25 a detection)."
    ]


def _hst(t: _Tables) -> list[str]:
    rows = t.rows("hst_result.csv")
    if not rows:
        return []
    r = rows[0]
    mle, lo, hi, n = _num(r["gamma_mle"]), _num(r["lower"]), _num(r["upper"]), r["n_images"]
    edge = _true(r["lower_at_edge"]) or _true(r["upper_at_edge"])
    text = (
        f"The {n} HST lenses combined read γ_MLE = {mle:.2f}, 68% interval [{lo:.2f}, "
        f"{hi:.2f}]" + (" (open at the prior edge: a bound at most)" if edge else "") + "."
    )
    from subslope.stages.summary_hst import null_ranges, null_scenes_holding

    nulls = null_ranges(t.rows("null_tests.csv"), n)
    inside = [scene for scene, _, _ in null_scenes_holding(mle, nulls)]
    if not t.read("null_tests.csv"):
        text += (
            " Not checked against the subhalo-free null stacks (null_tests.csv could not be "
            "read): until it is, the number is not a measurement of γ."
        )
    elif not nulls:
        text += (
            f" Not checked against the subhalo-free null stacks: no null scene is stacked "
            f"{n} deep, so the number is not a measurement of γ until one is."
        )
    elif inside:
        text += (
            f" That reading lies inside the 16–84% range of the {n}-image stacks of the "
            f"subhalo-free scenes ({', '.join(inside)}): the estimator cannot tell these "
            "lenses from images without subhalos, so the number is a symptom, not a "
            "measurement of γ."
        )
    elif nulls:
        text += f" It lies outside the 16–84% range of the subhalo-free {n}-image stacks."
    return [text]


def _domain(t: _Tables) -> list[str]:
    rows = t.rows("check_domain/domain_check.csv")
    if not rows or "outside" not in rows[0]:
        return []
    systems = {r["system"] for r in rows}
    outside = {r["system"] for r in rows if r.get("outside")}
    return [
        f"{len(systems) - len(outside)} of {len(systems)} HST lenses lie inside the "
        "simulated 1–99% range of every image statistic of the domain check."
    ]


def verdicts(results) -> list[str]:
    """One sentence per part of the campaign, computed from the CSVs of ``results``; a
    verdict whose table could not be read says "not checked", and the last sentence
    names every such table (:data:`SUMMARY_TABLES` missing, any table cut short)."""
    t = _Tables(Path(results))
    parts = (_in_distribution, _signal, _cdm, _figure4, _reference, _hst, _seeds, _domain)
    lines = [line for part in parts for line in part(t)]
    for name in SUMMARY_TABLES:
        t.rows(name)
    if t.unread:
        named = ", ".join(f"{name} ({why})" for name, why in sorted(t.unread.items()))
        lines.append(
            f"**Tables not read**: {named}. The verdicts that need them are not checked; "
            "rerun the campaign's write_summary (or the stage that writes the table)."
        )
    return lines


MEANING = """\
- **In-distribution reading and coverage** hold for images drawn from the training
  prior (EPL subhalos placed on the arcs, the simulated instrument). They say the
  estimator and its calibrated thresholds work where they were trained, nothing more.
- **The halo-free null test** is the pass criterion that γ is read from the halos: a
  failure would make every other number meaningless.
- **CDM predictions (figure 4)** are readings of simulated CDM populations by the same
  estimator. Where the paired shift against the same sets without subhalos is
  consistent with zero, the band is the estimator's response to subhalo-free images and
  cannot order NFW against tNFW or concentrations.
- **The HST result** is calibrated only as far as the 13 lenses look like the
  simulations (the domain check) and as far as the estimator responds to the subhalos
  they may hold. A reading inside the subhalo-free null range, or at a prior edge, is a
  symptom of an estimator that sees nothing, not a measured slope.
- The reduced campaign trains on far fewer images and a far smaller network than the
  paper (`config/config.yaml` comments each scale-down with the paper's value); its
  numbers test the pipeline, not the science case.
"""


def _command(record: dict[str, Any], config_line: str) -> str:
    files = record.get("config_files") or [f.strip() for f in config_line.split(",") if f]
    extra = "".join(f" --configfile {f}" for f in files if f != "config/config.yaml")
    return f"snakemake --cores 2{extra}"


def results_page(results, *, command: str | None = None) -> str:
    """The text of the results page of the campaign in ``results`` (a folder holding
    ``summary.md``; ``run.json`` where the campaign wrote one)."""
    results = Path(results)
    summary_path = results / "summary.md"
    if not summary_path.is_file():
        raise ResultsPageError(
            f"{summary_path} not found: results-page reads a finished campaign's results/ "
            "folder (rule write_summary writes summary.md)"
        )
    summary = summary_path.read_text(encoding="utf-8")
    record: dict[str, Any] = {}
    if (results / "run.json").is_file():
        record = json.loads((results / "run.json").read_text(encoding="utf-8"))
    config_line = next(
        (ln.split("`")[1] for ln in summary.splitlines() if ln.startswith("- config file")), ""
    )
    machine = record.get("machine") or {}
    when = record.get("finished_utc") or datetime.fromtimestamp(
        summary_path.stat().st_mtime, UTC
    ).strftime("%Y-%m-%d %H:%M")
    machine_text = (
        f"{machine.get('cpu')}, {machine.get('cores')} cores"
        + (f", {machine['gpu']}" if machine.get("gpu") else ", no GPU")
        + f"; torch {machine.get('torch')}"
        if machine
        else "not recorded (the campaign predates run.json)"
    )
    body = summary.split("\n", 1)[1] if "\n" in summary else ""
    # hashes belong to the dated records of the notebook, not to this page
    body = "\n".join(
        "#" + ln if ln.startswith("## ") else ln
        for ln in body.splitlines()
        if not ln.startswith("- config hash")
    )
    lines = [
        "# Results of the current campaign",
        "",
        "Generated by `subslope results-page results/` from the campaign's `results/` "
        "folder: regenerate it after a campaign, do not edit it by hand.",
        "",
        "| | |",
        "|---|---|",
        f"| command | `{command or _command(record, config_line)}` |",
        f"| config | `{config_line or '?'}` |",
        f"| machine | {machine_text} |",
        f"| finished (UTC) | {when} |",
        f"| subslope | {record.get('subslope', '?')} |",
        "",
        "## Verdict",
        "",
        *[f"- {v}" for v in verdicts(results)],
        "",
        "## What these numbers can and cannot be taken to mean",
        "",
        MEANING,
        *_seeds_section(results),
        "## The campaign's summary (`results/summary.md`)",
        body.rstrip(),
        "",
    ]
    return "\n".join(lines)


def _seeds_section(results: Path) -> list[str]:
    path = results / "seeds" / "seeds.md"
    if not path.is_file():
        return []
    return [
        "## Training seeds (`subslope seeds`, `results/seeds/seeds.md`)",
        "",
        path.read_text(encoding="utf-8").rstrip(),
        "",
    ]


def write_results_page(results, out, *, command: str | None = None) -> Path:
    """Write :func:`results_page` of ``results`` to ``out`` atomically; returns ``out``."""
    out = Path(out)
    write_text(out, results_page(results, command=command))
    return out
