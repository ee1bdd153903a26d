"""The systematics table: the campaign under several simulator variants, side by side
(``subslope systematics``; docs/systematics.md).

A *variant* is a config overlay with its own ``run_name`` (``config/variants/*.yaml``).
Its campaign config is the campaign's config, then ``systematics.common`` (e.g. smaller
sizes for every variant), then the overlay; it runs as a campaign of its own in
``<systematics.folder>/<run_name>/`` (its ``results/``, ``logs/`` and Snakemake state),
with the fetched data of the campaign (``data.resources_dir``) and one shard cache
(``systematics.shard_cache``, :mod:`subslope.io.shard_cache`): a shard that a variant does
not alter is simulated once for all of them. Each variant's Snakemake reruns only what
changed in it. The table then reads every variant's summary CSVs: the combined HST
γ_MLE and its calibrated interval, the a = 1 NFW and tNFW predictions, Spearman's ρ of
the EPL test stacks, the held-out coverage at N = 1 and at the largest N, the null-test
result and the number of HST lenses inside the simulated domain.
"""

from __future__ import annotations

import logging
import math
import os
import subprocess
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from subslope import config as _config
from subslope.io.atomic import write_csv, write_text
from subslope.plan import plan_problems

__all__ = [
    "SYSTEMATICS_COLUMNS",
    "Variant",
    "reference_config",
    "variant_config",
    "read_variants",
    "config_changes",
    "snakemake_command",
    "run_variant",
    "variant_row",
    "systematics_table",
]

log = logging.getLogger(__name__)

#: Keys of ``data`` holding paths relative to the campaign's working directory: a variant
#: runs in a folder of its own, so they are made absolute in its config.
DATA_PATH_KEYS = ("mirror", "resources_dir")

#: Columns of ``systematics.csv``, one row per variant.
SYSTEMATICS_COLUMNS = (
    "variant",
    "changes",
    "hst_gamma_mle",
    "hst_lower",
    "hst_upper",
    "hst_open",
    "nfw_median",
    "nfw_p16",
    "nfw_p84",
    "tnfw_median",
    "tnfw_p16",
    "tnfw_p84",
    "spearman_rho",
    "spearman_p",
    "coverage_n1",
    "coverage_n1_err",
    "n_max",
    "coverage_nmax",
    "coverage_nmax_err",
    "null_scene",
    "null_stack_excluding",
    "null_mean_profile_range",
    "domain_inside",
    "domain_lenses",
)


class SystematicsError(ValueError):
    """A variant file or a variant's results that cannot make a row."""


@dataclass(frozen=True)
class Variant:
    """One variant: its ``run_name``, overlay file, folder and merged campaign config."""

    name: str
    file: Path
    folder: Path
    config: dict[str, Any]


def _absolute(value: str, root: Path) -> str:
    return value if os.path.isabs(value) else str((root / value).resolve())


def reference_config(campaign: Mapping[str, Any]) -> dict[str, Any]:
    """The campaign's raw config with ``systematics.common`` merged in: what every
    variant's overlay sits on, and what the table's ``changes`` column is measured
    against."""
    common = (campaign.get("systematics") or {}).get("common") or {}
    return _config.deep_merge(campaign, common)


def variant_config(
    campaign: Mapping[str, Any],
    overlay: Mapping[str, Any],
    *,
    root: str | os.PathLike[str],
    shard_cache: str | os.PathLike[str],
) -> dict[str, Any]:
    """The raw config of one variant: ``campaign`` (raw keys), its
    ``systematics.common``, then ``overlay``; paths of :data:`DATA_PATH_KEYS` made absolute
    against ``root`` (the campaign's working directory), ``simulation.shard_cache`` set
    to ``shard_cache`` and the ``systematics`` section dropped (a variant runs no
    variants)."""
    root = Path(root)
    merged = _config.deep_merge(reference_config(campaign), overlay)
    merged.pop("systematics", None)
    merged.pop(_config.BASE_KEY, None)
    data = merged.setdefault("data", {})
    defaults = _config.schema_defaults("data")
    for key in DATA_PATH_KEYS:
        value = data.get(key, defaults.get(key))
        if value is not None:
            data[key] = _absolute(str(value), root)
    merged.setdefault("simulation", {})["shard_cache"] = _absolute(str(shard_cache), root)
    return merged


def read_variants(
    campaign: Mapping[str, Any], *, root: str | os.PathLike[str] = "."
) -> list[Variant]:
    """The variants of ``campaign`` (raw keys; ``systematics.variants``), each overlay
    read with its layers, merged (:func:`variant_config`) and validated, the checks the
    workflow makes before its first job included (:func:`subslope.plan.plan_problems`),
    so that no variant runs while a later one cannot. Raises
    :class:`SystematicsError` naming the file for an overlay without its own
    ``run_name``, two variants of one name, or an invalid merged config."""
    root = Path(root)
    section = _config.validate(campaign)["systematics"]
    folder = Path(_absolute(section["folder"], root))
    variants: list[Variant] = []
    seen: dict[str, Path] = {}
    for entry in section["variants"]:
        file = Path(_absolute(entry, root))
        if not file.is_file():
            raise SystematicsError(f"systematics.variants: variant file {file} does not exist")
        overlay = _config.read_files([file])
        name = overlay.get("run_name")
        if not name or name == campaign.get("run_name"):
            raise SystematicsError(
                f"variant file {file}: it must set a run_name of its own (the variant's "
                f"folder and the table's row are named by it); got {name!r}"
            )
        if name in seen:
            raise SystematicsError(
                f"variant files {seen[name]} and {file} both have run_name {name!r}"
            )
        seen[name] = file
        merged = variant_config(campaign, overlay, root=root, shard_cache=section["shard_cache"])
        try:
            problems = plan_problems(_config.validate(merged))
        except _config.ConfigError as exc:
            raise SystematicsError(f"variant file {file}: {exc}") from None
        if problems:  # every variant is checked before the first one runs
            listed = "\n".join(f"  - {p}" for p in problems)
            raise SystematicsError(f"variant file {file}: invalid configuration:\n{listed}")
        variants.append(Variant(name, file, folder / name, merged))
    return variants


def _leaves(tree: Any, prefix: tuple[str, ...] = ()) -> dict[tuple[str, ...], Any]:
    if isinstance(tree, Mapping) and tree:
        out: dict[tuple[str, ...], Any] = {}
        for key, value in tree.items():
            out.update(_leaves(value, (*prefix, str(key))))
        return out
    return {prefix: tree}


def config_changes(reference: Mapping[str, Any], variant: Mapping[str, Any]) -> str:
    """The keys in which the validated ``variant`` differs from the validated
    ``reference``, as ``key=value`` joined by '; '; a change made in several scenes is
    written once, as ``scenes.{a,b}.key`` (``scenes.*.key`` when in every scene the
    variant simulates). Paths and ``run_name`` are not listed."""
    ignore = {("run_name",), ("simulation", "shard_cache")}
    ignore |= {("data", key) for key in DATA_PATH_KEYS}
    old = _leaves(_config.validate(reference))
    full = _config.validate(variant)
    new = _leaves(full)
    grouped: dict[tuple[tuple[str, ...], str], list[str]] = {}
    for key in sorted(set(old) | set(new)):
        if key in ignore or key[:1] == ("systematics",) or old.get(key) == new.get(key):
            continue
        value = yaml.safe_dump(new.get(key), default_flow_style=True).strip()
        value = value.removesuffix("...").strip()
        if key[0] == "scenes" and len(key) > 2:
            grouped.setdefault((("scenes", "{}", *key[2:]), value), []).append(key[1])
        else:
            grouped.setdefault((key, value), [])
    scenes = {n for n, c in full["simulation"]["scenes"].items() if c["n_shards"] > 0}
    parts = []
    for (key, value), names in grouped.items():
        if names:
            label = "*" if set(names) >= scenes else "{" + ",".join(names) + "}"
            key = tuple(label if k == "{}" else k for k in key)
        parts.append(f"{'.'.join(key)}={value}")
    return "; ".join(parts) or "none"


def snakemake_command(
    variant: Variant, *, snakefile: str | os.PathLike[str], cores: int, extra: Sequence[str] = ()
) -> list[str]:
    """The Snakemake call that runs ``variant`` in its folder (``extra``: more arguments,
    e.g. ``--profile profiles/slurm``)."""
    exe = Path(sys.executable).with_name("snakemake")
    return [
        str(exe) if exe.exists() else "snakemake",
        "--snakefile",
        str(Path(snakefile).resolve()),
        "--directory",
        str(variant.folder),
        "--configfile",
        str(variant.folder / "config.yaml"),
        "--cores",
        str(int(cores)),
        *extra,
    ]


def run_variant(
    variant: Variant, *, snakefile: str | os.PathLike[str], cores: int, extra: Sequence[str] = ()
) -> None:
    """Write ``variant``'s config into its folder (only when it changed, so a rerun of an
    unchanged variant has nothing to do) and run its campaign; a failed campaign raises
    :class:`subprocess.CalledProcessError` (its log is in the variant's folder)."""
    variant.folder.mkdir(parents=True, exist_ok=True)
    path = variant.folder / "config.yaml"
    text = (
        f"# Campaign config of the systematics variant {variant.name} ({variant.file}),\n"
        "# written by `subslope systematics`: edit the variant file, not this one.\n"
        + yaml.safe_dump(variant.config, sort_keys=False)
    )
    if not path.exists() or path.read_text(encoding="utf-8") != text:
        write_text(path, text)
    command = snakemake_command(variant, snakefile=snakefile, cores=cores, extra=extra)
    log.info("variant %s: %s", variant.name, " ".join(command))
    run_to_end(command)


#: Seconds an interrupted Snakemake gets to stop its jobs and release its lock.
STOP_GRACE_S = 300


def run_to_end(command: Sequence[str]) -> None:
    """Run ``command`` (a Snakemake call) like ``subprocess.run(check=True)``, except on
    Ctrl-C: the child is not killed (``subprocess.run`` would, leaving Snakemake's lock
    and incomplete markers behind) but interrupted and waited for, so that it stops its
    jobs and releases its lock; then KeyboardInterrupt is raised again. SIGINT is sent
    only if the terminal's did not reach it, SIGTERM only after :data:`STOP_GRACE_S`."""
    import signal

    proc = subprocess.Popen(list(command))
    try:
        code = proc.wait()
    except KeyboardInterrupt:
        try:
            proc.wait(timeout=2)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=STOP_GRACE_S)
            except subprocess.TimeoutExpired:
                proc.terminate()
                proc.wait()
        raise
    if code:
        raise subprocess.CalledProcessError(code, list(command))


def _read_csv(path: Path, **kwargs):
    import pandas as pd

    if not path.is_file():
        raise SystematicsError(f"{path} is missing: the variant's campaign did not finish")
    return pd.read_csv(path, **kwargs)


def _cdm(cdm, scene: str | None, prefix: str) -> dict[str, float]:
    rows = cdm[cdm["scene"] == scene] if scene else cdm.iloc[0:0]
    if rows.empty:
        return {f"{prefix}_{k}": math.nan for k in ("median", "p16", "p84")}
    r = rows.iloc[0]
    return {f"{prefix}_{k}": float(r[k]) for k in ("median", "p16", "p84")}


def variant_row(results: str | os.PathLike[str], config: Mapping[str, Any]) -> dict[str, Any]:
    """One row of the table from a campaign's ``results`` folder (its summary CSVs and
    the domain check) and its validated ``config``."""
    results = Path(results)
    hst = _read_csv(results / "hst_result.csv").iloc[0]
    cdm = _read_csv(results / "cdm_prediction.csv")
    coverage = _read_csv(results / "coverage.csv").set_index("n_images")
    trend = _read_csv(results / "trend.csv").iloc[0]
    null = _read_csv(results / "null_tests.csv")
    domain = _read_csv(results / "check_domain" / "domain_check.csv", keep_default_na=False)
    n_max = int(max(coverage.index))
    null_row = null.iloc[-1] if len(null) else None
    inside = domain["inside"].astype(str).str.lower() == "true"
    return {
        "hst_gamma_mle": float(hst["gamma_mle"]),
        "hst_lower": float(hst["lower"]),
        "hst_upper": float(hst["upper"]),
        "hst_open": "/".join(
            side
            for side, flag in (("lower", hst["lower_at_edge"]), ("upper", hst["upper_at_edge"]))
            if str(flag).lower() == "true"
        )
        or "no",
        **_cdm(cdm, config["cdm"]["nfw_scene"], "nfw"),
        **_cdm(cdm, config["cdm"]["tnfw_scene"], "tnfw"),
        "spearman_rho": float(trend["rho"]),
        "spearman_p": float(trend["p_value"]),
        "coverage_n1": float(coverage.loc[1, "coverage"]) if 1 in coverage.index else math.nan,
        "coverage_n1_err": float(coverage.loc[1, "coverage_err"])
        if 1 in coverage.index
        else math.nan,
        "n_max": n_max,
        "coverage_nmax": float(coverage.loc[n_max, "coverage"]),
        "coverage_nmax_err": float(coverage.loc[n_max, "coverage_err"]),
        "null_scene": "" if null_row is None else str(null_row["scene"]),
        "null_stack_excluding": math.nan
        if null_row is None
        else float(null_row["stack_excluding"]),
        "null_mean_profile_range": math.nan
        if null_row is None
        else float(null_row["mean_profile_range"]),
        "domain_inside": int(inside.sum()),
        "domain_lenses": len(domain),
    }


def _markdown(rows: Sequence[Mapping[str, Any]]) -> str:
    head = (
        "| variant | HST γ_MLE [68%] | NFW a=1 | tNFW a=1 | ρ (p) | coverage N=1 | "
        "coverage N=max | null: stacks excluding, profile range | domain | changes |\n"
        "|---|---|---|---|---|---|---|---|---|---|\n"
    )

    def band(r: Mapping[str, Any], p: str) -> str:
        if math.isnan(r[f"{p}_median"]):
            return "–"
        return f"{r[f'{p}_median']:.2f} [{r[f'{p}_p16']:.2f}, {r[f'{p}_p84']:.2f}]"

    lines = []
    for r in rows:
        opened = "" if r["hst_open"] == "no" else f" open {r['hst_open']}"
        lines.append(
            f"| {r['variant']} | {r['hst_gamma_mle']:.2f} [{r['hst_lower']:.2f}, "
            f"{r['hst_upper']:.2f}]{opened} | {band(r, 'nfw')} | {band(r, 'tnfw')} | "
            f"{r['spearman_rho']:.2f} ({r['spearman_p']:.2g}) | "
            f"{r['coverage_n1']:.2f} ± {r['coverage_n1_err']:.2f} | "
            f"{r['coverage_nmax']:.2f} ± {r['coverage_nmax_err']:.2f} (N={r['n_max']}) | "
            f"{r['null_stack_excluding']:.2f}, {r['null_mean_profile_range']:.3f} nats "
            f"({r['null_scene']}) | {r['domain_inside']}/{r['domain_lenses']} | "
            f"{r['changes']} |"
        )
    return head + "\n".join(lines) + "\n"


def systematics_table(
    variants: Sequence[Variant],
    reference: Mapping[str, Any],
    out_dir: str | os.PathLike[str],
    *,
    run_name: str,
) -> list[dict[str, Any]]:
    """``systematics.csv``, ``systematics.md`` and ``figures/systematics.{pdf,png}`` in
    ``out_dir`` from the finished variant campaigns; ``reference`` (the campaign's raw
    config with ``systematics.common``) is what the ``changes`` column is measured
    against. Returns the rows."""
    from subslope.figures.save import save_figure
    from subslope.figures.systematics import systematics_figure

    out_dir = Path(out_dir)
    rows = []
    for v in variants:
        cfg = _config.validate(v.config)
        row = {"variant": v.name, "changes": config_changes(reference, v.config)}
        row.update(variant_row(v.folder / "results", cfg))
        rows.append(row)
    write_csv(out_dir / "systematics.csv", rows, list(SYSTEMATICS_COLUMNS))
    write_text(out_dir / "systematics.md", _markdown(rows))
    level = float(_config.validate(reference)["calibration"]["level"])
    fig = systematics_figure(rows, level=level, run_name=run_name)
    save_figure(fig, out_dir / "figures" / "systematics", run_name=run_name)
    return rows
