"""Logging set-up shared by the workflow scripts (one log file per Snakemake job), and
the record of a job that started and has not finished.

Every output of the workflow is flagged ``update()``: when a job fails, Snakemake puts
the previous version of its outputs back, but records the failed job's parameters on
it, so the next run would take a file made under the old config for one made under the
new. Each job therefore leaves a record naming its outputs under :data:`RECORDS` when it
starts and removes it only when it ends without an exception; a job killed or failed
leaves it. When the workflow loads, :func:`mark_unfinished_outputs` sets the time stamp
of every output such a record names to the epoch, older than any input: the job runs
again, and until it succeeds nothing downstream takes the restored file for new.
"""

from __future__ import annotations

import atexit
import hashlib
import json
import logging
import os
import sys
from collections.abc import Iterable
from pathlib import Path

__all__ = [
    "LOG_FORMAT",
    "RECORDS",
    "job_started",
    "log_to_file",
    "mark_unfinished_outputs",
    "forget_jobs_of",
]

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"

#: Folder (relative to the workflow's working directory) of the records of running jobs.
RECORDS = Path(".subslope") / "running"


def log_to_file(path: str, level: int = logging.INFO, *, outputs: Iterable[str] = ()) -> None:
    """Send every log record of this process (package loggers included) to ``path``; with
    ``outputs`` (the job's output files) record the job as started (:func:`job_started`)."""
    logging.basicConfig(filename=path, level=level, format=LOG_FORMAT)
    outputs = [str(o) for o in outputs]
    if outputs:
        job_started(outputs)


def _record_path(outputs: list[str], root: Path) -> Path:
    key = hashlib.sha256("\0".join(sorted(outputs)).encode()).hexdigest()[:32]
    return root / RECORDS / f"{key}.json"


def job_started(outputs: Iterable[str], root: str | os.PathLike[str] = ".") -> Path:
    """Record that the job writing ``outputs`` runs; the record goes when this process
    exits without an uncaught exception. Returns the record's path."""
    outputs = sorted(str(o) for o in outputs)
    record = _record_path(outputs, Path(root))
    record.parent.mkdir(parents=True, exist_ok=True)
    tmp = record.with_name(f".{record.name}.{os.getpid()}")
    tmp.write_text(json.dumps(outputs) + "\n", encoding="utf-8")
    os.replace(tmp, record)
    failed = []
    previous = sys.excepthook

    def hook(kind, value, tb):
        failed.append(kind)
        previous(kind, value, tb)

    sys.excepthook = hook
    atexit.register(lambda: None if failed else record.unlink(missing_ok=True))
    return record


def mark_unfinished_outputs(root: str | os.PathLike[str] = ".") -> list[Path]:
    """Set the time stamp of every existing output named by a record of a job that did not
    finish to the epoch (so that Snakemake runs the job again); returns those files."""
    folder = Path(root) / RECORDS
    marked = []
    for record in sorted(folder.glob("*.json")) if folder.is_dir() else []:
        try:
            outputs = json.loads(record.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        for name in outputs:
            path = Path(root) / name
            if path.is_file() and path.stat().st_mtime > 0:
                os.utime(path, (0, 0))
                marked.append(path)
    return marked


def forget_jobs_of(
    files: Iterable[str | os.PathLike[str]], root: str | os.PathLike[str] = "."
) -> int:
    """Remove the records of unfinished jobs all of whose outputs are among ``files``
    (outputs put in place by other means, such as a data file restored from the mirror,
    whose failed fetch must not make them look stale); returns how many went."""
    folder = Path(root) / RECORDS
    done = {os.path.normpath(os.fspath(f)) for f in files}
    gone = 0
    for record in sorted(folder.glob("*.json")) if folder.is_dir() and done else []:
        try:
            outputs = json.loads(record.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if outputs and {os.path.normpath(o) for o in outputs} <= done:
            record.unlink(missing_ok=True)
            gone += 1
    return gone
