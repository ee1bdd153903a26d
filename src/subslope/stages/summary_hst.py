"""The HST part of ``summary.md``: the combined result against the subhalo-free null
stacks, each lens's influence (leave-one-out), the spread over trainings
(``subslope seeds``) and one sentence on what the number can be taken to mean."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from subslope.io.atomic import write_csv
from subslope.stages.markdown import fmt, md_table

__all__ = [
    "HST_COLUMNS",
    "hst_section",
    "against_null_stacks",
    "null_ranges",
    "null_scenes_holding",
    "leave_one_out_lines",
    "seeds_markdown",
    "seeds_lines",
    "meaning_lines",
    "reach_lines",
]

#: Columns of ``hst_result.csv``: the combined stack of the HST lenses.
HST_COLUMNS = (
    "n_images",
    "gamma_mle",
    "lower",
    "upper",
    "minus",
    "plus",
    "threshold",
    "threshold_n",
    "lower_at_edge",
    "upper_at_edge",
    "multimodal",
)


def hst_section(folder: Path, hst_csv, null_csv=None) -> list[str]:
    """The combined HST result and every lens's (``results/analyze_hst/hst_result.csv``);
    writes ``hst_result.csv`` (:data:`HST_COLUMNS`) into ``folder``."""
    import pandas as pd

    if not hst_csv:
        write_csv(
            folder / "hst_result.csv",
            [],
            HST_COLUMNS,
        )
        return ["Stage `hst` not run.\n"]
    hst = pd.read_csv(hst_csv)
    comb = hst[hst["system"] == "combined"].iloc[0]
    row = {
        "n_images": int(comb["n_images"]),
        "gamma_mle": float(comb["mle"]),
        "lower": float(comb["lower"]),
        "upper": float(comb["upper"]),
        "minus": float(comb["mle"] - comb["lower"]),
        "plus": float(comb["upper"] - comb["mle"]),
        "threshold": float(comb["threshold"]),
        "threshold_n": int(comb["threshold_n"]),
        "lower_at_edge": bool(comb["lower_at_edge"]),
        "upper_at_edge": bool(comb["upper_at_edge"]),
        "multimodal": bool(comb["multimodal"]),
    }
    write_csv(folder / "hst_result.csv", [row])
    note = []
    if row["threshold_n"] != row["n_images"]:
        note.append(
            f"threshold from N = {row['threshold_n']}, NOT calibrated for N = {row['n_images']}"
        )
    if row["lower_at_edge"] or row["upper_at_edge"]:
        note.append("open at the prior edge")
    if row["multimodal"]:
        note.append("hull of several regions")
    singles = hst[hst["system"] != "combined"].to_dict("records")
    return [
        f"Combined stack of {row['n_images']} HST lenses: γ_MLE = {row['gamma_mle']:.3f} "
        f"(−{row['minus']:.3f}, +{row['plus']:.3f}) at {fmt(row['threshold'])} "
        f"(68% interval [{row['lower']:.3f}, {row['upper']:.3f}])"
        + (f"; {'; '.join(note)}" if note else "")
        + ".\n",
        *against_null_stacks(row["gamma_mle"], row["n_images"], null_csv),
        md_table(
            singles,
            ["system", "mle", "lower", "upper", "lower_at_edge", "upper_at_edge"]
            + (["inside_domain"] if "inside_domain" in hst.columns else []),
        ),
    ]


def _null_ranges(null_csv, n_images: int) -> list[tuple[str, float, float]]:
    """:func:`null_ranges` of the rows of ``null_tests.csv`` (none without the file)."""
    import pandas as pd

    if not null_csv:
        return []
    return null_ranges(pd.read_csv(null_csv).to_dict("records"), n_images)


def null_ranges(rows, n_images) -> list[tuple[str, float, float]]:
    """(scene, 16%, 84%) of the stack γ_MLE of every subhalo-free null scene stacked
    ``n_images`` deep; ``rows``: the rows of ``null_tests.csv`` as mappings (numbers or
    their text)."""
    return [
        (str(r["scene"]), float(r["stack_mle_p16"]), float(r["stack_mle_p84"]))
        for r in rows
        if int(float(r["n_per_stack"])) == int(float(n_images))
    ]


def null_scenes_holding(mle: float, ranges) -> list[tuple[str, float, float]]:
    """The :func:`null_ranges` whose 16–84% range holds the combined γ_MLE ``mle``: where
    the HST reading does not tell the lenses from images without subhalos (the verdict
    of the summary and of the results page alike)."""
    return [(scene, lo, hi) for scene, lo, hi in ranges if lo <= mle <= hi]


def against_null_stacks(mle: float, n_images: int, null_csv) -> list[str]:
    """Where the HST combined γ_MLE falls among the stack γ_MLE of the subhalo-free null
    scenes stacked as many images deep (``null_tests.csv``): inside their 16–84% range
    it does not tell the HST lenses from images without subhalos."""
    ranges = _null_ranges(null_csv, n_images)
    if not ranges:
        return []
    holding = null_scenes_holding(mle, ranges)
    parts = [
        f"{scene} {'inside' if (scene, lo, hi) in holding else 'outside'} [{lo:.2f}, {hi:.2f}]"
        for scene, lo, hi in ranges
    ]
    return [
        f"Against the {n_images}-image stacks of the subhalo-free null scenes (16–84% of "
        f"their γ_MLE): {'; '.join(parts)}. Inside that range the combined γ_MLE does not "
        "tell the HST lenses from images without subhalos.\n"
    ]


def leave_one_out_lines(loo_csv, highlight: Sequence[str] = ()) -> list[str]:
    """The combined γ_MLE with each HST lens left out (results/analyze_hst/leave_one_out.csv);
    ``highlight`` (``hst.highlight``): lenses the config singles out, named where the set
    holds them."""
    import pandas as pd

    if not loo_csv:
        return []
    table = pd.read_csv(loo_csv)
    if not len(table):
        return []
    top = table.loc[table["shift"].abs().idxmax()]
    shown = [name for name in highlight if name in set(table["left_out"])]
    named = f"; highlighted in the config (hst.highlight): {', '.join(shown)}" if shown else ""
    return [
        "\nThe combined stack with each lens left out (`shift`: its γ_MLE minus that of "
        f"all lenses; threshold of {int(table['n_images'].iloc[0])}-image stacks). The "
        f"largest shift comes from leaving out {top['left_out']} ({top['shift']:+.3f})"
        f"{named}:\n",
        md_table(table.to_dict("records"), ["left_out", "mle", "lower", "upper", "shift"]),
    ]


def seeds_markdown(rows: Sequence[Mapping[str, Any]]) -> str:
    """The table of ``seeds.csv`` (one row per training of the estimator) and one sentence
    on the spread of the HST reading over the trainings."""
    lines = [
        "| training | seed | HST γ_MLE [68%] | open | NFW a=1 | tNFW a=1 | ρ | coverage N=max |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['training']} | {r['seed']} | {float(r['hst_gamma_mle']):.2f} "
            f"[{float(r['hst_lower']):.2f}, {float(r['hst_upper']):.2f}] | {r['hst_open']} | "
            f"{float(r['nfw_median']):.2f} | {float(r['tnfw_median']):.2f} | "
            f"{float(r['spearman_rho']):.2f} | {float(r['coverage_nmax']):.2f} "
            f"(N={int(r['n_max'])}) |"
        )
    g = np.array([float(r["hst_gamma_mle"]) for r in rows], dtype=np.float64)
    n_open = sum(str(r["hst_open"]) != "no" for r in rows)
    sd = f", standard deviation {np.std(g, ddof=1):.2f}" if g.size > 1 else ""
    lines += [
        "",
        f"Over {g.size} trainings the combined HST γ_MLE spans {g.min():.2f}–{g.max():.2f}"
        f" ({g.max() - g.min():.2f}{sd}); {n_open} of {g.size} intervals are open at a "
        "prior edge.",
    ]
    return "\n".join(lines) + "\n"


def _seed_rows(seeds_csv) -> list[dict[str, Any]]:
    import pandas as pd

    if not seeds_csv or not Path(seeds_csv).is_file():
        return []
    table = pd.read_csv(seeds_csv, dtype={"seed": str, "hst_open": str})
    return table.to_dict("records")


def seeds_lines(seeds_csv) -> list[str]:
    """The HST reading of every training of the estimator (``results/seeds/seeds.csv``,
    written by ``subslope seeds``); a pointer to the command where there is none."""
    rows = _seed_rows(seeds_csv)
    if not rows:
        return [
            "\nOne training of the estimator: `subslope seeds` trains it again with other "
            "seeds and puts the spread of this reading here.\n"
        ]
    return [
        "\nThe same campaign's estimator trained with other seeds (`subslope seeds`, "
        "results/seeds/; every training sees the same images):\n",
        seeds_markdown(rows),
    ]


def meaning_lines(hst_result_csv, null_csv=None, seeds_csv=None) -> list[str]:
    """One sentence on what the combined HST γ_MLE can be taken to mean: not a measurement
    where it lies inside the range the subhalo-free null stacks read, where its interval
    is open at a prior edge, or where it moves between trainings by more than its own 68%
    half-width; a measurement otherwise."""
    import pandas as pd

    if not Path(hst_result_csv).is_file():
        return []
    table = pd.read_csv(hst_result_csv)
    if not len(table):
        return []
    row = table.iloc[0]
    mle, lo, hi = float(row["gamma_mle"]), float(row["lower"]), float(row["upper"])
    reasons = []
    ranges = _null_ranges(null_csv, int(row["n_images"]))
    inside = [
        f"{scene} [{lo16:.2f}, {hi84:.2f}]"
        for scene, lo16, hi84 in null_scenes_holding(mle, ranges)
    ]
    if inside:
        reasons.append(
            f"it lies inside the 16–84% range of the subhalo-free null stacks ({', '.join(inside)})"
        )
    if bool(row["lower_at_edge"]) or bool(row["upper_at_edge"]):
        reasons.append("its 68% interval is open at a prior edge")
    g = [float(r["hst_gamma_mle"]) for r in _seed_rows(seeds_csv)]
    half = (hi - lo) / 2
    if len(g) > 1 and max(g) - min(g) > half:
        reasons.append(
            f"it moves by {max(g) - min(g):.2f} between {len(g)} trainings, more than its "
            f"68% half-width {half:.2f}"
        )
    if reasons:
        text = (
            f"What the number means: γ_MLE = {mle:.2f} is not a measurement of the subhalos' "
            f"slope, because {'; '.join(reasons)}."
        )
    elif not ranges:
        text = (
            f"What the number means: not checked. The {int(row['n_images'])} lenses read "
            f"γ = {mle:.2f} [{lo:.2f}, {hi:.2f}] (68%), but no subhalo-free null scene is "
            f"stacked {int(row['n_images'])} deep (null_tests.csv), so whether the reading "
            "differs from that of images without subhalos is not known."
        )
    else:
        spread = f", stable to {max(g) - min(g):.2f} over {len(g)} trainings" if g else ""
        text = (
            f"What the number means: the {int(row['n_images'])} lenses read γ = {mle:.2f} "
            f"[{lo:.2f}, {hi:.2f}] (68%), outside the subhalo-free range{spread}; it is a "
            "measurement under the training prior's model of the subhalos."
        )
    return [f"\n**{text}**\n"]


def reach_lines(hst_result_csv, signal_csv=None, scenes: Sequence[str | None] = ()) -> list[str]:
    """What the HST lenses could show at all, from the signal budget
    (``results/signal_budget/signal_budget.csv``): the refitted Δχ² that CDM subhalos
    (a = 1, each of ``scenes``) and the training scene's would leave in as many images as
    the HST stack holds (that many × the median per image)."""
    import pandas as pd

    if not signal_csv or not Path(hst_result_csv).is_file():
        return []
    hst = pd.read_csv(hst_result_csv)
    if not len(hst):
        return []
    n = int(hst["n_images"].iloc[0])
    table = pd.read_csv(signal_csv)
    parts = []
    for scene in [s for s in scenes if s]:
        rows = table[(table["scene"] == scene) & (pd.to_numeric(table["multiplier"]) == 1.0)]
        if len(rows):
            parts.append(f"{n * float(rows['refit_p50'].iloc[0]):.3g} ({scene})")
    train = table[table["scene"] == "train"]
    if not parts or not len(train):
        return []
    return [
        f"\nWhat {n} lenses could show at all (signal budget): CDM subhalos at a = 1 would "
        f"leave a stack of {n} images a Δχ² of {' and '.join(parts)} after a full refit of "
        f"the smooth model, against {n * float(train['refit_p50'].iloc[0]):.3g} for {n} "
        "training images (Δχ² ≈ 25: one individual detection).\n"
    ]
