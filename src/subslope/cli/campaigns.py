"""The ``subslope`` commands that act on whole campaigns.

systematics [--config C ...] [--cores N] [--only NAME ...] [--table-only] [-- SNAKEMAKE ARGS]
    Run the campaign under every variant of systematics.variants (each in its own folder,
    sharing the data and the shard cache) and write the systematics table and figure.
seeds [--config C ...] [--seeds K ...] [--cores N] [--table-only] [-- SNAKEMAKE ARGS]
    Train the campaign's estimator again with other seeds (each a campaign in its own
    folder, sharing the data and the shard cache), write the spread of the readings and
    bring the campaign's results/summary.md up to date with it.
cache du|prune [--config C ...]
    What the shard cache holds and what uses it; remove what no config uses.
cluster-jobs [--total] -- SNAKEMAKE ARGS
    The cluster jobs a campaign submits (its dry run, a group counted once).
compare-runs BASELINE NEW [--ignore-attr NAME ...]
    Two campaigns' results/ folders, number by number (exit 1 when anything differs).
results-page RESULTS [--out docs/results.md] [--command CMD]
    The page of a finished campaign's results (docs/results.md), generated.
cost [--config C ...] [--results DIR] [--gpu-images-per-s N] [-- SNAKEMAKE ARGS]
    What a campaign costs: shard jobs, CPU-hours of simulation, disk of the shards,
    GPU-hours of training (and, given Snakemake arguments, its cluster jobs).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["add_campaign_commands"]


#: What an interrupted campaign command says: Snakemake stopped with its lock released,
#: and the same command resumes (profiles/default/config.yaml: rerun-incomplete).
INTERRUPTED = (
    "interrupted while running {name}: Snakemake stopped its jobs and released its lock; "
    "run the same command again to resume (the interrupted jobs run again)"
)


def add_campaign_commands(commands) -> None:
    """Add the commands of this module to the ``subslope`` sub-parsers ``commands``."""
    _add_systematics_command(commands)
    _add_seeds_command(commands)
    _add_cache_command(commands)
    _add_cluster_jobs_command(commands)
    _add_compare_runs_command(commands)
    _add_results_page_command(commands)
    _add_cost_command(commands)


def _systematics(args: argparse.Namespace) -> int:
    import subprocess

    from subslope.campaigns.systematics import (
        SystematicsError,
        read_variants,
        reference_config,
        run_variant,
        systematics_table,
    )
    from subslope.config import ConfigError, read_files, validate

    files = args.config or ["config/config.yaml"]
    try:
        raw = read_files(files)
        section = validate(raw)["systematics"]
        variants = read_variants(raw, root=Path.cwd())
    except (ConfigError, SystematicsError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if args.only:
        unknown = sorted(set(args.only) - {v.name for v in variants})
        if unknown:
            known = ", ".join(v.name for v in variants) or "none"
            print(f"error: --only {unknown}: no such variant (known: {known})", file=sys.stderr)
            return 1
        variants = [v for v in variants if v.name in args.only]
    if not variants:
        print(f"error: {', '.join(files)}: systematics.variants is empty", file=sys.stderr)
        return 1
    extra = [a for a in args.snakemake_args if a != "--"]
    snakefile = Path(args.snakefile)
    for variant in variants if not args.table_only else []:
        try:
            run_variant(variant, snakefile=snakefile, cores=args.cores, extra=extra)
        except KeyboardInterrupt:
            print(INTERRUPTED.format(name=f"variant {variant.name}"), file=sys.stderr)
            return 130
        except subprocess.CalledProcessError as exc:
            print(
                f"error: the campaign of variant {variant.name} failed (exit {exc.returncode});"
                f" its logs are in {variant.folder}/logs",
                file=sys.stderr,
            )
            return 1
    try:
        systematics_table(
            variants, reference_config(raw), section["table"], run_name=raw["run_name"]
        )
    except SystematicsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {section['table']}/systematics.csv, .md and figures/systematics.*")
    return 0


def _seeds(args: argparse.Namespace) -> int:
    import subprocess

    from subslope.campaigns.seeds import SEEDS_CSV, seed_variants, seeds_table, summary_command
    from subslope.campaigns.systematics import SystematicsError, run_to_end, run_variant
    from subslope.config import ConfigError, read_files

    files = args.config or ["config/config.yaml"]
    out = Path(args.folder)
    try:
        raw = read_files(files)
        variants = seed_variants(raw, args.seeds, root=Path.cwd(), folder=out, file=files[-1])
    except (ConfigError, SystematicsError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    extra = [a for a in args.snakemake_args if a != "--"]
    for variant in variants if not args.table_only else []:
        try:
            run_variant(variant, snakefile=Path(args.snakefile), cores=args.cores, extra=extra)
        except KeyboardInterrupt:
            print(INTERRUPTED.format(name=variant.name), file=sys.stderr)
            return 130
        except subprocess.CalledProcessError as exc:
            print(
                f"error: the campaign of {variant.name} failed (exit {exc.returncode}); its "
                f"logs are in {variant.folder}/logs",
                file=sys.stderr,
            )
            return 1
    try:
        _, text = seeds_table(raw, args.results, variants, out)
    except SystematicsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(text, end="")
    print(f"wrote {out}/seeds.csv and seeds.md")
    if args.table_only or out.resolve() != Path(SEEDS_CSV).parent.resolve():
        return 0
    command = summary_command(files, snakefile=args.snakefile, cores=args.cores, extra=extra)
    try:
        run_to_end(command)
    except KeyboardInterrupt:
        print(INTERRUPTED.format(name="the summary"), file=sys.stderr)
        return 130
    except subprocess.CalledProcessError as exc:
        print(f"error: updating results/summary.md failed (exit {exc.returncode})", file=sys.stderr)
        return 1
    print("results/summary.md holds the table")
    return 0


def _add_seeds_command(commands) -> None:
    p = commands.add_parser(
        "seeds", help="train the estimator again with other seeds; the spread of its readings"
    )
    p.add_argument(
        "--seeds", nargs="+", type=int, default=[1, 2],
        help="training seeds besides the campaign's own (default 1 2: three trainings)",
    )  # fmt: skip
    p.add_argument(
        "--results", default="results", help="the campaign's own finished results/ folder"
    )
    p.add_argument(
        "--folder", default="results/seeds", help="where the seeds' campaigns and table go"
    )
    _add_campaign_run_arguments(p, "seed")
    p.set_defaults(func=_seeds)


def _cache(args: argparse.Namespace) -> int:
    from collections import defaultdict

    from subslope.campaigns.cache import cache_usage, campaigns_in_use, format_size, prune_cache
    from subslope.campaigns.systematics import SystematicsError
    from subslope.config import ConfigError

    files = args.config or ["config/config.yaml"]
    try:
        usage = cache_usage(campaigns_in_use(files))
    except (ConfigError, SystematicsError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if not usage:
        print(f"{', '.join(files)}: no campaign keeps a cache (simulation.shard_cache is null)")
        return 0
    if args.action == "prune":
        removed, kept = prune_cache(usage, force=args.force, dry_run=args.dry_run)
        verb = "would remove" if args.dry_run else "removed"
        print(f"{verb} {len(removed)} entries, {format_size(sum(e.size for e in removed))}")
        if kept:
            print(
                f"kept {len(kept)} unreferenced entries ({format_size(sum(e.size for e in kept))})"
                " that results/ files still link; --force removes them (freeing no space"
                " while those files exist)"
            )
        return 0
    for folder, entries in usage.items():
        print(f"{folder}: {len(entries)} entries, {format_size(sum(e.size for e in entries))}")
        rows: dict[str, list] = defaultdict(lambda: [0, 0, 0, 0, 0])
        for entry in entries:
            row = rows[entry.group]
            row[0] += 1
            row[1] += entry.size
            row[2] += entry.held
            row[3] += bool(entry.used_by)
            row[4] += 0 if entry.used_by else entry.size
        header = ("scene / kind", "entries", "size", "linked", "in use", "unused size")
        print("  {:<20} {:>8} {:>10} {:>7} {:>7} {:>12}".format(*header))
        for group, (n, size, held, used, free) in sorted(rows.items()):
            line = (group, n, format_size(size), held, used, format_size(free))
            print("  {:<20} {:>8} {:>10} {:>7} {:>7} {:>12}".format(*line))
        for entry in entries if args.entries else []:
            where = "linked" if entry.held else "cache only"
            users = ", ".join(entry.used_by) or "-"
            print(f"  {entry.group}/{entry.key[:16]}  {format_size(entry.size)}  {where}", end="")
            print(f"  used by: {users}")
    print(
        "linked: another name (a results/ file) links the entry; in use: a shard job or fit "
        f"of {', '.join(files)} or of its systematics variants would take it"
    )
    return 0


def _cluster_jobs(args: argparse.Namespace) -> int:
    import subprocess

    from subslope.plan import count_cluster_jobs, host_rules

    snakemake = Path(sys.executable).with_name("snakemake")
    extra = [a for a in args.snakemake_args if a != "--"]
    proc = subprocess.run([str(snakemake), "-n", *extra], capture_output=True, text=True)
    if proc.returncode != 0:
        sys.stderr.write(proc.stdout[-3000:] + proc.stderr[-3000:])
        print(f"error: snakemake -n {' '.join(extra)} failed", file=sys.stderr)
        return proc.returncode
    jobs = count_cluster_jobs(proc.stdout, host_rules(Path.cwd()))
    total = sum(jobs.values())
    if not args.total:
        width = max(map(len, jobs), default=12)
        for key, n in sorted(jobs.items(), key=lambda item: (-item[1], item[0])):
            print(f"{key:<{width}}  {n:>6}")
        print(f"{'cluster jobs':<{width}}  {total:>6}")
    else:
        print(total)
    return 0


def _add_cluster_jobs_command(commands) -> None:
    p = commands.add_parser(
        "cluster-jobs",
        help="the cluster jobs a campaign submits (its snakemake -n, a group counted once)",
    )
    p.add_argument("--total", action="store_true", help="print the total only")
    p.add_argument(
        "snakemake_args", nargs=argparse.REMAINDER,
        help="after --: the Snakemake arguments, e.g. -- --profile profiles/slurm "
        "--configfile config/paper.yaml",
    )  # fmt: skip
    p.set_defaults(func=_cluster_jobs)


def _add_cache_command(commands) -> None:
    p = commands.add_parser(
        "cache", help="size of the shard cache and what uses it (du), or prune unused entries"
    )
    p.add_argument("action", choices=["du", "prune"], help="du: report; prune: remove unused")
    p.add_argument(
        "--config", nargs="+", default=None,
        help="the configs in use, each read as --configfile, with their systematics variants"
        " (default config/config.yaml)",
    )  # fmt: skip
    p.add_argument("--entries", action="store_true", help="du: list every entry")
    p.add_argument(
        "--force", action="store_true", help="prune: also entries that results/ files link"
    )
    p.add_argument(
        "--dry-run", action="store_true", help="prune: list what would go, remove nothing"
    )
    p.set_defaults(func=_cache)


def _add_systematics_command(commands) -> None:
    p = commands.add_parser(
        "systematics", help="the campaign under every simulator variant, and their table"
    )
    p.add_argument("--only", nargs="+", default=None, help="run_names of the variants to run")
    _add_campaign_run_arguments(p, "variant")
    p.set_defaults(func=_systematics)


def _add_campaign_run_arguments(p, what: str) -> None:
    """The arguments of a command that runs campaigns in folders of their own."""
    p.add_argument(
        "--config", nargs="+", default=None,
        help="campaign config file(s), read as --configfile (default config/config.yaml)",
    )  # fmt: skip
    p.add_argument("--cores", type=int, default=2, help=f"cores of each {what}'s Snakemake")
    p.add_argument(
        "--table-only", action="store_true", help=f"write the table from finished {what}s"
    )
    p.add_argument("--snakefile", default="Snakefile", help="the workflow (default ./Snakefile)")
    p.add_argument(
        "snakemake_args", nargs=argparse.REMAINDER,
        help="after --: more Snakemake arguments, e.g. -- --profile profiles/slurm",
    )  # fmt: skip


def _compare_runs(args: argparse.Namespace) -> int:
    from subslope.campaigns.compare import compare_trees

    failed = compare_trees(args.baseline, args.new, tuple(args.ignore_attr))
    print(f"{failed} file(s) differ" if failed else "all compared files are identical")
    return 1 if failed else 0


def _add_compare_runs_command(commands) -> None:
    from subslope.campaigns.compare import DEFAULT_IGNORED_ATTRS

    p = commands.add_parser(
        "compare-runs", help="two campaigns' results/ folders, number by number"
    )
    p.add_argument("baseline", type=Path, help="results/ folder of the reference run")
    p.add_argument("new", type=Path, help="results/ folder of the run to check")
    p.add_argument(
        "--ignore-attr", action="append", default=list(DEFAULT_IGNORED_ATTRS),
        help="HDF5 attribute allowed to differ (repeatable)",
    )  # fmt: skip
    p.set_defaults(func=_compare_runs)


def _results_page(args: argparse.Namespace) -> int:
    from subslope.campaigns.results_page import ResultsPageError, write_results_page

    try:
        out = write_results_page(args.results, args.out, command=args.command)
    except ResultsPageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {out}")
    return 0


def _add_results_page_command(commands) -> None:
    p = commands.add_parser(
        "results-page", help="docs/results.md from a finished campaign's results/ folder"
    )
    p.add_argument("results", type=Path, help="the campaign's results/ folder")
    p.add_argument("--out", type=Path, default=Path("docs/results.md"), help="the page")
    p.add_argument(
        "--command", default=None,
        help="the command that made the campaign (default: read from results/run.json)",
    )  # fmt: skip
    p.set_defaults(func=_results_page)


def _cost(args: argparse.Namespace) -> int:
    from subslope.campaigns.cost import (
        DEFAULT_BYTES_PER_IMAGE,
        DEFAULT_GPU_IMAGES_PER_S,
        DEFAULT_SECONDS_PER_IMAGE,
        campaign_cost,
        measured_costs,
    )
    from subslope.config import ConfigError, load

    try:
        config = load(args.config or ["config/config.yaml"], env=False)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    measured = measured_costs(args.results) if args.results else {}
    where = f"measured on {args.results}" if args.results else ""
    sources = {
        "seconds_per_image": where if "seconds_per_image" in measured else "stated default",
        "bytes_per_image": where if "bytes_per_image" in measured else "stated default",
        "gpu_images_per_s": "given" if args.gpu_images_per_s else "stated default (paper, V100)",
    }
    cost = campaign_cost(
        config,
        seconds_per_image=measured.get("seconds_per_image", DEFAULT_SECONDS_PER_IMAGE),
        bytes_per_image=measured.get("bytes_per_image", DEFAULT_BYTES_PER_IMAGE),
        gpu_images_per_s=args.gpu_images_per_s or DEFAULT_GPU_IMAGES_PER_S,
        sources=sources,
    )
    print(f"shard jobs            {cost.shard_jobs:>12,}")
    print(f"images simulated      {cost.images:>12,}")
    print(
        f"CPU-hours, simulation {cost.cpu_hours_simulation:>12,.1f}"
        f"  ({cost.seconds_per_image * 1e3:.1f} ms a training image, "
        f"{sources['seconds_per_image']}; other scenes priced by their N_sub and profile)"
    )
    for name, hours in list(cost.cpu_hours_by_scene.items())[:6]:
        print(f"  {name:<20}{hours:>12,.1f}")
    print(
        f"disk of the shards    {cost.disk_gb_shards:>12,.1f} GB"
        f"  ({cost.bytes_per_image / 1e3:.1f} KB/image, {sources['bytes_per_image']})"
    )
    print(f"GPU-hours, training   {cost.gpu_hours_training:>12,.1f}"
          f"  ({cost.training_images:,} images x {cost.max_epochs} epochs at most, "
          f"{cost.gpu_images_per_s:.0f} images/s, {sources['gpu_images_per_s']})")  # fmt: skip
    extra = [a for a in args.snakemake_args if a != "--"]
    if extra:
        return _cluster_jobs(argparse.Namespace(snakemake_args=extra, total=False))
    return 0


def _add_cost_command(commands) -> None:
    p = commands.add_parser(
        "cost", help="shard jobs, CPU-hours, disk and GPU-hours of a campaign before it runs"
    )
    p.add_argument(
        "--config", nargs="+", default=None, help="config file(s) (default config/config.yaml)"
    )
    p.add_argument(
        "--results", type=Path, default=None,
        help="a finished campaign's results/ folder: its measured cost per image",
    )  # fmt: skip
    p.add_argument(
        "--gpu-images-per-s", type=float, default=None,
        help="training images per second of one GPU (default: the paper's V100 figure)",
    )  # fmt: skip
    p.add_argument(
        "snakemake_args", nargs=argparse.REMAINDER,
        help="after --: Snakemake arguments to count the cluster jobs too, e.g. "
        "-- --profile profiles/slurm --configfile config/paper.yaml",
    )  # fmt: skip
    p.set_defaults(func=_cost)
