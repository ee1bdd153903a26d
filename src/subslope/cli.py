"""Command-line interface: ``subslope <command> ...``.

Commands
--------
validate-config PATH
    Check a workflow config file against the schema; print the full configuration
    (defaults filled) or the problems, each naming its key.
fetch-data --mirror DIR --dest DIR [--allow-download]
    Materialise the checksummed data files under DIR (as the workflow's fetch_data rule).

Later stages add their sub-commands in :func:`build_parser`.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

import yaml

from subslope import __version__

__all__ = ["main", "build_parser"]


def _validate_config(args: argparse.Namespace) -> int:
    from subslope.config import ConfigError, load

    try:
        config = load(args.path, env=False)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if not args.quiet:
        sys.stdout.write(yaml.safe_dump(config, sort_keys=False))
    print(f"{args.path}: valid", file=sys.stderr)
    return 0


def _fetch_data(args: argparse.Namespace) -> int:
    from subslope.resources import ResourceError, fetch

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:
        files = fetch(args.dest, mirror=args.mirror, allow_download=args.allow_download)
    except ResourceError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"{len(files)} files verified under {args.dest}", file=sys.stderr)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="subslope",
        description="Subhalo effective density slope from strong-lensing images.",
    )
    parser.add_argument("--version", action="version", version=f"subslope {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = commands.add_parser("validate-config", help="check a workflow config file against the schema")
    p.add_argument("path", help="YAML config file, e.g. config/config.yaml")
    p.add_argument("-q", "--quiet", action="store_true", help="do not print the filled configuration")
    p.set_defaults(func=_validate_config)

    p = commands.add_parser("fetch-data", help="copy/download and verify the data files")
    p.add_argument("--mirror", default=None, help="local folder with hst/, psf/, cosmos/ (tried first)")
    p.add_argument("--dest", default="resources", help="destination folder (default: resources)")
    p.add_argument(
        "--allow-download", action="store_true",
        help="download files missing from the mirror from their public URLs",
    )
    p.set_defaults(func=_fetch_data)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``subslope`` console script; returns the exit status."""
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
