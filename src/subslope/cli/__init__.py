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

The commands over whole campaigns (systematics, seeds, cache, cluster-jobs, compare-runs,
results-page, cost) are in :mod:`subslope.cli.campaigns`; ``observations add|check`` (a
set of real lenses of one's own) in :mod:`subslope.cli.observations`.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path

import yaml

from subslope._version import __version__
from subslope.cli.campaigns import add_campaign_commands
from subslope.cli.observations import add_observation_commands

__all__ = ["main", "build_parser"]


def _validate_config(args: argparse.Namespace) -> int:
    """Check a config as the workflow does: relative paths resolved against the project
    folder (:func:`subslope.plan.project_root`), whatever the working directory."""
    import contextlib

    from subslope.config import ConfigError, active_stages, load
    from subslope.plan import plan_problems, plan_warnings, project_root

    path = Path(args.path).resolve()
    root = project_root(path)
    with contextlib.chdir(root):
        try:
            config = load(path, env=False)
        except ConfigError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
        problems = plan_problems(config)
        warnings = [] if problems else plan_warnings(config, root)
    for warning in warnings:
        print(f"warning: {warning}", file=sys.stderr)
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
    from subslope.plan import shard_job_config
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

    from subslope.figures.gallery import plot_scene_examples_from_shard
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
            from subslope.plan import shard_job_config
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
            config=config,
            loo_csv=out / "leave_one_out.csv",
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
    add_campaign_commands(commands)
    add_observation_commands(commands)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``subslope`` console script; returns the exit status."""
    args = build_parser().parse_args(argv)
    return args.func(args)
