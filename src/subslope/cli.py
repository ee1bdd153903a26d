"""Command-line interface: ``subslope <command> ...``.

Commands
--------
validate-config PATH [--cluster]
    Check a workflow config file as the workflow does when it loads (the file on its
    ``base``, the schema, the scenes, the data, the devices of this machine unless
    ``--cluster``); print the full configuration or the problems, each naming its key.
fetch-data --mirror DIR --dest DIR [--allow-download]
    Materialise the checksummed data files under DIR (as the workflow's fetch_data rule).

simulate --config C --scene S --shard K --out PATH [--multiplier A] [--overwrite]
    Simulate one shard of images (as the workflow's simulate_shard rule).
preview --config C --scene S [--n 8] --out FIG.png
    Simulate a few images of a scene (in a temporary shard) and plot them with their
    arc masks, to look at a scene before running the workflow.
train --config C --train SHARD... --val SHARD... --whitening J --out DIR [--ckpt DIR]
    Train (or resume) the estimator with the config's training section (as the
    workflow's train_estimator rule): DIR/model.pt and DIR/training_log.csv.
analyze-hst --config C --model M --thresholds J --out DIR [--hst DIR] [--cdm CSV]
    Profiles, intervals and figures 5-6 of the real HST lenses (as rule analyze_hst).
systematics [--config C ...] [--cores N] [--only NAME ...] [--table-only] [-- SNAKEMAKE ARGS]
    Run the campaign under every variant of systematics.variants (each in its own folder,
    sharing the data and the shard cache) and write the systematics table and figure.

Later stages add their sub-commands in :func:`build_parser`.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence

import yaml

from subslope._version import __version__

__all__ = ["main", "build_parser"]


def _validate_config(args: argparse.Namespace) -> int:
    from subslope.config import ConfigError, active_stages, load
    from subslope.stages.plan import plan_problems

    try:
        config = load(args.path, env=False)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    problems = plan_problems(config)
    if not args.cluster:
        from subslope.devices import device_problems

        problems += device_problems(config, active_stages(config))
    if problems:
        print("error: " + "\n  - ".join(["invalid configuration:", *problems]), file=sys.stderr)
        return 1
    if not args.quiet:
        sys.stdout.write(yaml.safe_dump(config, sort_keys=False))
    print(f"{args.path}: valid", file=sys.stderr)
    return 0


def _fetch_data(args: argparse.Namespace) -> int:
    from subslope.io.resources import ResourceError, fetch

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:
        files = fetch(args.dest, mirror=args.mirror, allow_download=args.allow_download)
    except ResourceError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"{len(files)} files verified under {args.dest}", file=sys.stderr)
    return 0


def _load_config(path):
    from subslope.config import ConfigError, load

    try:
        return load(path)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return None


def _simulate(args: argparse.Namespace) -> int:
    from subslope.io.shards import ShardError
    from subslope.stages.plan import shard_job_config
    from subslope.stages.simulate import simulate_shard_job

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    config = _load_config(args.config)
    if config is None:
        return 1
    try:
        if os.path.exists(args.out) and not args.overwrite:
            raise FileExistsError(f"shard {args.out} already exists; pass --overwrite")
        # The workflow's own job: the same file, byte for byte, as rule simulate_shard.
        job = shard_job_config(config, args.scene, args.multiplier)
        path = simulate_shard_job(
            job, config, args.scene, args.shard, args.out, multiplier=args.multiplier
        )
    except (FileExistsError, ShardError, ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {path}", file=sys.stderr)
    return 0


def _preview(args: argparse.Namespace) -> int:
    import copy
    import math
    import tempfile

    from subslope.figures.data import plot_scene_examples_from_shard
    from subslope.simulation.resolve import resolved_scene, scene_multipliers
    from subslope.simulation.shard import simulate_shard

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    config = _load_config(args.config)
    if config is None:
        return 1
    try:
        scene, _ = resolved_scene(config, args.scene)
        k = scene.images_per_set
        cfg = copy.deepcopy(config)
        cfg["simulation"]["scenes"][args.scene] = {
            "n_shards": 1,
            "images_per_shard": k * math.ceil(args.n / k),
        }
        mults = scene_multipliers(cfg, scene)
        multiplier = (
            None
            if mults is None
            else (
                args.multiplier
                if args.multiplier is not None
                else (1.0 if 1.0 in mults else mults[0])
            )
        )
        with tempfile.TemporaryDirectory() as tmp:
            shard = simulate_shard(
                cfg, args.scene, 0, f"{tmp}/preview.h5", multiplier=multiplier, progress=True
            )
            plot_scene_examples_from_shard(
                shard, [args.out], run_name=f"{config['run_name']} (preview)", n=args.n
            )
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


def _train(args: argparse.Namespace) -> int:
    from pathlib import Path

    from subslope.stages.train import run_training, training_section

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    config = _load_config(args.config)
    if config is None:
        return 1
    ckpt = args.ckpt or str(Path(args.out) / "checkpoints")
    streamed = config["training"]["data"] == "stream"
    if streamed == bool(args.train):
        print(
            "error: "
            + (
                "training.data is 'stream': the training images are simulated, give no --train"
                if streamed
                else "--train: give the training shard files (or set training.data: stream)"
            ),
            file=sys.stderr,
        )
        return 1
    try:
        stream = None
        if streamed:
            from subslope.config import STREAMED_SCENE
            from subslope.stages.plan import shard_job_config
            from subslope.stages.simulate import runnable_config

            stream = runnable_config(shard_job_config(config, STREAMED_SCENE), config)
        summary = run_training(
            training_section(config),
            args.train or [],
            args.val,
            args.whitening,
            args.out,
            ckpt,
            device=config["training"]["device"],
            stream=stream,
        )
    except (ValueError, FileNotFoundError, RuntimeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(
        f"wrote {summary['model']} ({summary['epochs']} epochs, stop: {summary['stop_reason']})",
        file=sys.stderr,
    )
    return 0


def _analyze_hst(args: argparse.Namespace) -> int:
    from pathlib import Path

    from subslope.stages.hst import analyze_hst
    from subslope.stats.intervals import gamma_grid

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    config = _load_config(args.config)
    if config is None:
        return 1
    out = Path(args.out)
    hst, grid = config["hst"], config["inference"]["gamma_grid"]
    folder = args.hst or str(Path(config["data"]["resources_dir"]) / "hst")
    try:
        table = analyze_hst(
            args.model,
            folder,
            args.thresholds,
            out / "profiles.h5",
            out / "intervals.csv",
            out / "fig5_hst_profiles",
            out / "fig6_hst_combined",
            run_name=config["run_name"],
            gammas=gamma_grid(grid["low"], grid["high"], grid["n"]),
            cdm_csv=args.cdm,
            combine=hst["combine"],
            show=hst["show"],
            highlight=hst["highlight"],
            lens_centre=hst["lens_centre"],
            pixel_scale=config["instrument"]["pixel_scale"],
            device=config["inference"]["device"],
            nfw_scene=config["cdm"]["nfw_scene"],
            tnfw_scene=config["cdm"]["tnfw_scene"],
        )
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(table.to_string(index=False))
    return 0


def _domain_check(args: argparse.Namespace) -> int:
    from subslope.stages.domain import domain_check_cli

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    config = _load_config(args.config)
    if config is None:
        return 1
    try:
        table = domain_check_cli(
            config, args.scene, args.n, args.out, whitening_json=args.whitening, seed=args.seed
        )
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(table.to_string(index=False))
    print(
        f"{int(table['inside'].sum())} of {len(table)} HST lenses inside; "
        f"wrote {args.out}/domain_check.csv",
        file=sys.stderr,
    )
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="subslope", description="Subhalo effective density slope from strong-lensing images."
    )
    parser.add_argument("--version", action="version", version=f"subslope {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = commands.add_parser(
        "validate-config", help="check a workflow config file against the schema"
    )
    p.add_argument("path", help="YAML config file, e.g. config/config.yaml")
    p.add_argument(
        "-q", "--quiet", action="store_true", help="do not print the filled configuration"
    )
    p.add_argument(
        "--cluster",
        action="store_true",
        help="the jobs run elsewhere: do not check the devices against this machine",
    )
    p.set_defaults(func=_validate_config)

    p = commands.add_parser("fetch-data", help="copy/download and verify the data files")
    p.add_argument(
        "--mirror", default=None, help="local folder with hst/, psf/, cosmos/ (tried first)"
    )
    p.add_argument("--dest", default="resources", help="destination folder (default: resources)")
    p.add_argument(
        "--allow-download",
        action="store_true",
        help="download files missing from the mirror from their public URLs",
    )
    p.set_defaults(func=_fetch_data)

    p = commands.add_parser("simulate", help="simulate one shard of images")
    p.add_argument("--config", required=True, help="workflow config file")
    p.add_argument("--scene", required=True, help="scene name (a key of simulation.scenes)")
    p.add_argument("--shard", required=True, type=int, help="shard index (0 .. n_shards - 1)")
    p.add_argument("--out", required=True, help="output HDF5 file (must not exist)")
    p.add_argument(
        "--multiplier", type=float, default=None, help="concentration multiplier a (CDM scenes)"
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing file")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_simulate)

    p = commands.add_parser("preview", help="plot a few simulated images of a scene")
    p.add_argument("--config", required=True, help="workflow config file")
    p.add_argument("--scene", required=True, help="scene name")
    p.add_argument("--n", type=int, default=8, help="number of images (default 8)")
    p.add_argument(
        "--multiplier", type=float, default=None, help="concentration multiplier a (CDM scenes)"
    )
    p.add_argument("--out", required=True, help="figure file (.png, .pdf)")
    p.set_defaults(func=_preview)

    p = commands.add_parser(
        "train", help="train (or resume training) the likelihood-ratio estimator"
    )
    p.add_argument("--config", required=True, help="workflow config file (its training section)")
    p.add_argument(
        "--train",
        nargs="*",
        default=[],
        help="training shard files (none with training.data: stream)",
    )
    p.add_argument("--val", required=True, nargs="+", help="validation shard files")
    p.add_argument("--whitening", required=True, help="whitening JSON (rule compute_whitening)")
    p.add_argument("--out", required=True, help="folder for model.pt and training_log.csv")
    p.add_argument(
        "--ckpt", default=None, help="checkpoint folder (default OUT/checkpoints); resumed from"
    )
    p.set_defaults(func=_train)
    _add_real_data_commands(commands)
    return parser


def _add_real_data_commands(commands) -> None:
    """The commands that read the real HST lenses: analyze-hst, domain-check."""
    p = commands.add_parser(
        "analyze-hst", help="profiles, intervals and figures of the real HST lenses"
    )
    p.add_argument("--config", required=True, help="workflow config file (hst, inference sections)")
    p.add_argument("--model", required=True, help="model.pt of the estimator")
    p.add_argument("--thresholds", required=True, help="thresholds.json (rule summarize_coverage)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--hst", default=None, help="HST cutout folder (default <resources_dir>/hst)")
    p.add_argument("--cdm", default=None, help="cdm_grid.csv for the a = 1 bands of figure 6")
    p.set_defaults(func=_analyze_hst)

    p = commands.add_parser(
        "domain-check",
        help="simulate N images of a scene and compare their statistics with the HST lenses",
    )
    p.add_argument("--config", required=True, help="workflow config file")
    p.add_argument("--scene", default="train", help="scene name (default train)")
    p.add_argument("--n", type=int, default=1000, help="simulated images (default 1000)")
    p.add_argument("--out", required=True, help="output folder (domain_check.csv, figures)")
    p.add_argument(
        "--whitening",
        default=None,
        help="whitening JSON (rule compute_whitening); default: the simulated images' own",
    )
    p.add_argument("--seed", type=int, default=None, help="seed (default: the config's)")
    p.set_defaults(func=_domain_check)
    _add_systematics_command(commands)
    _add_cache_command(commands)
    _add_cluster_jobs_command(commands)


def _systematics(args: argparse.Namespace) -> int:
    import subprocess
    from pathlib import Path

    from subslope.config import ConfigError, read_files, validate
    from subslope.stages.systematics import (
        SystematicsError,
        read_variants,
        reference_config,
        run_variant,
        systematics_table,
    )

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


def _cache(args: argparse.Namespace) -> int:
    from collections import defaultdict

    from subslope.config import ConfigError
    from subslope.stages.cache import cache_usage, campaigns_in_use, format_size, prune_cache
    from subslope.stages.systematics import SystematicsError

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
    from pathlib import Path

    from subslope.stages.plan import count_cluster_jobs, host_rules

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
    p.add_argument(
        "--config", nargs="+", default=None,
        help="campaign config file(s), read as --configfile (default config/config.yaml)",
    )  # fmt: skip
    p.add_argument("--cores", type=int, default=2, help="cores of each variant's Snakemake")
    p.add_argument("--only", nargs="+", default=None, help="run_names of the variants to run")
    p.add_argument(
        "--table-only", action="store_true", help="write the table from finished variants"
    )
    p.add_argument("--snakefile", default="Snakefile", help="the workflow (default ./Snakefile)")
    p.add_argument(
        "snakemake_args", nargs=argparse.REMAINDER,
        help="after --: more Snakemake arguments, e.g. -- --profile profiles/slurm",
    )  # fmt: skip
    p.set_defaults(func=_systematics)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``subslope`` console script; returns the exit status."""
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
