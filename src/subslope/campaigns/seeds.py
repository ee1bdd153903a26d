"""Training seeds: the campaign's estimator trained again with other seeds, and how far
what it reads moves from one training to the next (``subslope seeds``; docs/workflow.md).

Each seed runs as a campaign of its own in ``<folder>/<run_name>_seed<k>/`` (as a
systematics variant does, :mod:`subslope.campaigns.systematics`): the campaign's config
with ``training.seed: k``, the same fetched data and the same shard cache, so its shards
are copied from the cache, not simulated again. Stages that do not depend on the
estimator (gallery, domain check, signal budget, halo-free and visibility null tests,
scene examples) are switched off in it. The table puts the campaign's own result beside
the seeds': the combined HST γ_MLE with its calibrated interval, the a = 1 CDM readings,
Spearman's ρ of the EPL test stacks and the coverage at the largest N, and the spread of
the HST reading over all trainings. The campaign's ``results/summary.md`` shows the table
when :data:`SEEDS_CSV` exists; ``subslope seeds`` brings the summary up to date after it.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from subslope import config as _config
from subslope.campaigns.systematics import SystematicsError, Variant, _read_csv, variant_config
from subslope.io.atomic import write_csv, write_text
from subslope.plan import plan_problems
from subslope.stages.summary_hst import seeds_markdown

__all__ = [
    "SEEDS_COLUMNS",
    "ESTIMATOR_ONLY",
    "seed_variants",
    "seed_row",
    "seeds_table",
    "seeds_markdown",
    "SEEDS_CSV",
    "summary_command",
]

#: What a seed's campaign leaves out: the stages that do not read the estimator.
ESTIMATOR_ONLY: dict[str, Any] = {
    "stages": {"gallery": False, "domain": False, "signal_budget": False},
    "null_tests": {"halo_free_sets": 0, "cdm_visibility": False},
    "simulation": {"scene_examples": False},
}

#: Where the campaign's summary looks for the table of trainings (rule write_summary).
SEEDS_CSV = "results/seeds/seeds.csv"

#: Columns of ``seeds.csv``, one row per training.
SEEDS_COLUMNS = (
    "training",
    "seed",
    "hst_gamma_mle",
    "hst_lower",
    "hst_upper",
    "hst_open",
    "nfw_median",
    "tnfw_median",
    "spearman_rho",
    "n_max",
    "coverage_nmax",
)


def seed_variants(
    campaign: Mapping[str, Any],
    seeds: Sequence[int],
    *,
    root: str | os.PathLike[str],
    folder: str | os.PathLike[str],
    file: str | os.PathLike[str],
) -> list[Variant]:
    """One variant per training seed of ``campaign`` (raw keys), checked as the workflow
    checks a config before its first job. ``folder``: where the seeds' campaigns run;
    ``file``: the campaign's config file (named in each variant's config)."""
    run = campaign["run_name"]
    cache = _config.validate(campaign)["simulation"]["shard_cache"]
    if cache is None:
        raise SystematicsError(
            "simulation.shard_cache is null: the seeds' campaigns would simulate every shard "
            "again; set a cache folder (e.g. .cache/shard_cache)"
        )
    out = []
    for seed in dict.fromkeys(int(s) for s in seeds):
        if not 0 <= seed < 2**32:
            raise SystematicsError(f"training seed {seed} is outside 0 .. 2^32-1")
        name = f"{run}_seed{seed}"
        overlay = _config.deep_merge(ESTIMATOR_ONLY, {"run_name": name, "training": {"seed": seed}})
        # the campaign itself: systematics.common (smaller variants) does not apply
        own = {k: v for k, v in campaign.items() if k != "systematics"}
        merged = variant_config(own, overlay, root=root, shard_cache=cache)
        try:
            problems = plan_problems(_config.validate(merged))
        except _config.ConfigError as exc:
            raise SystematicsError(f"training seed {seed}: {exc}") from None
        if problems:
            listed = "\n".join(f"  - {p}" for p in problems)
            raise SystematicsError(f"training seed {seed}: invalid configuration:\n{listed}")
        out.append(Variant(name, Path(file), Path(folder) / name, merged))
    return out


def seed_row(results: str | os.PathLike[str], config: Mapping[str, Any]) -> dict[str, Any]:
    """What one training reads, from a finished campaign's ``results`` folder."""
    results = Path(results)
    hst = _read_csv(results / "hst_result.csv").iloc[0]
    cdm = _read_csv(results / "cdm_prediction.csv").set_index("scene")
    coverage = _read_csv(results / "coverage.csv").set_index("n_images")
    trend = _read_csv(results / "trend.csv").iloc[0]
    n_max = int(max(coverage.index))

    def cdm_median(scene):
        return float(cdm.loc[scene, "median"]) if scene in cdm.index else math.nan

    edges = [s for s in ("lower", "upper") if str(hst[f"{s}_at_edge"]).lower() == "true"]
    seed = config["training"]["seed"]
    return {
        "seed": "derived" if seed is None else int(seed),
        "hst_gamma_mle": float(hst["gamma_mle"]),
        "hst_lower": float(hst["lower"]),
        "hst_upper": float(hst["upper"]),
        "hst_open": "/".join(edges) or "no",
        "nfw_median": cdm_median(config["cdm"]["nfw_scene"]),
        "tnfw_median": cdm_median(config["cdm"]["tnfw_scene"]),
        "spearman_rho": float(trend["rho"]),
        "n_max": n_max,
        "coverage_nmax": float(coverage.loc[n_max, "coverage"]),
    }


def seeds_table(
    campaign: Mapping[str, Any],
    results: str | os.PathLike[str],
    variants: Sequence[Variant],
    out_dir: str | os.PathLike[str],
) -> tuple[list[dict[str, Any]], str]:
    """``seeds.csv`` and ``seeds.md`` in ``out_dir``: the campaign's own training (its
    ``results`` folder) and every seed's, and the spread of the HST reading. Returns the
    rows and the markdown."""
    rows = [{"training": campaign["run_name"], **seed_row(results, _config.validate(campaign))}]
    for v in variants:
        rows.append(
            {"training": v.name, **seed_row(v.folder / "results", _config.validate(v.config))}
        )
    write_csv(Path(out_dir) / "seeds.csv", rows, list(SEEDS_COLUMNS))
    text = seeds_markdown(rows)
    write_text(Path(out_dir) / "seeds.md", text)
    return rows, text


def summary_command(
    files: Sequence[str],
    *,
    snakefile: str | os.PathLike[str],
    cores: int,
    extra: Sequence[str] = (),
) -> list[str]:
    """The Snakemake call that brings the campaign's own ``results/summary.md`` up to date
    once :data:`SEEDS_CSV` is written (the summary reads the table when it exists)."""
    exe = Path(sys.executable).with_name("snakemake")
    configs = [a for f in files for a in ("--configfile", str(f))]
    return [
        str(exe) if exe.exists() else "snakemake",
        "--snakefile",
        str(Path(snakefile).resolve()),
        *configs,
        "--cores",
        str(int(cores)),
        "results/summary.md",
        *extra,
    ]
