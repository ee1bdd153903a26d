"""Logging set-up shared by the workflow scripts (one log file per Snakemake job)."""

from __future__ import annotations

import logging

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def log_to_file(path: str, level: int = logging.INFO) -> None:
    """Send every log record of this process (package loggers included) to ``path``."""
    logging.basicConfig(filename=path, level=level, format=LOG_FORMAT)
