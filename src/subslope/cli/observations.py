"""The ``subslope observations`` commands: record and check a set of real lenses.

observations add FOLDER [--catalog NAME] [--config C ...]
    Check every cutout of FOLDER against the config's simulated instrument and write
    FOLDER/manifest.sha256 (refused, naming file and reason, if any cutout fails).
observations check [--config C ...]
    Check the configured set (observations.folder) as the workflow does before a run.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["add_observation_commands"]


def _config(files):
    from subslope.config import read_files, validate

    return validate(read_files(files or ["config/config.yaml"]))


def _add(args: argparse.Namespace) -> int:
    from subslope.config import ConfigError
    from subslope.io.observation_set import cutout_problems, write_manifest
    from subslope.plan import theta_e_warnings

    folder = Path(args.folder)
    catalog = folder / args.catalog
    try:
        config = _config(args.config)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    problems = cutout_problems(config, folder, catalog)
    if problems:
        print(f"error: {folder}: no manifest written:", file=sys.stderr)
        for p in problems:
            print(f"  - {p}", file=sys.stderr)
        return 1
    for w in theta_e_warnings(config, catalog):
        print(f"warning: {w}", file=sys.stderr)
    path = write_manifest(folder, catalog)
    print(f"wrote {path}; use it with observations: {{folder: {folder}, catalog: {args.catalog}}}")
    return 0


def _check(args: argparse.Namespace) -> int:
    from subslope.config import ConfigError
    from subslope.io.observation_set import observation_folder
    from subslope.plan import plan_problems, theta_e_warnings

    try:
        config = _config(args.config)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    folder, catalog, shipped = observation_folder(config)
    problems = plan_problems(config)
    if problems:
        print("error: " + "\n  - ".join(["invalid configuration:", *problems]), file=sys.stderr)
        return 1
    for w in theta_e_warnings(config, catalog) if catalog.is_file() else []:
        print(f"warning: {w}", file=sys.stderr)
    what = "the shipped lenses (checked by the data registry)" if shipped else str(catalog)
    print(f"{what}: valid")
    return 0


def add_observation_commands(commands) -> None:
    """Add ``observations add`` and ``observations check`` to the sub-parsers ``commands``."""
    p = commands.add_parser("observations", help="record and check a set of real lenses")
    sub = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    add = sub.add_parser("add", help="check a folder of cutouts and write its manifest")
    add.add_argument("folder", help="folder of the cutouts and their catalogue")
    add.add_argument("--catalog", default="catalog.csv", help="catalogue file in the folder")
    add.add_argument(
        "--config", nargs="+", default=None, help="config file(s) (instrument, priors)"
    )
    add.set_defaults(func=_add)
    check = sub.add_parser("check", help="check the configured set as a run does")
    check.add_argument("--config", nargs="+", default=None, help="config file(s)")
    check.set_defaults(func=_check)
