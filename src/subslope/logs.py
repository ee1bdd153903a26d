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

The record also holds a fingerprint of the job's parameters; a job that finishes leaves
that fingerprint and the SHA-256 and time stamp of each output under :data:`MADE`. A
restored output whose content is what a job of the same parameters made (an interrupted
forced rerun with the config unchanged) is correct as it is: its record is dropped and
it gets back the time stamp it was made with (Snakemake's restore writes a fresh copy),
so nothing downstream reruns.
"""

from __future__ import annotations

import atexit
import hashlib
import json
import logging
import os
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

__all__ = [
    "LOG_FORMAT",
    "RECORDS",
    "MADE",
    "params_fingerprint",
    "job_started",
    "log_to_file",
    "mark_unfinished_outputs",
    "forget_jobs_of",
]

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"

#: Folder (relative to the workflow's working directory) of the records of running jobs.
RECORDS = Path(".subslope") / "running"
#: Folder of the parameter fingerprints of the jobs that made the current outputs.
MADE = Path(".subslope") / "made"


def log_to_file(
    path: str, level: int = logging.INFO, *, outputs: Iterable[str] = (), params: Any = None
) -> None:
    """Send every log record of this process (package loggers included) to ``path``; with
    ``outputs`` (the job's output files) record the job as started (:func:`job_started`,
    ``params``: the job's Snakemake parameters)."""
    logging.basicConfig(filename=path, level=level, format=LOG_FORMAT)
    outputs = [str(o) for o in outputs]
    if outputs:
        job_started(outputs, params=params)


def params_fingerprint(params: Any) -> str | None:
    """32 hex digits of the SHA-256 of a job's parameters (a Snakemake ``params`` object
    or a mapping; values that are not JSON as their text), or None without parameters."""
    if params is None:
        return None
    items = dict(params.items()) if hasattr(params, "items") else dict(params)
    text = json.dumps(items, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def _mtime_ns(path: Path) -> int | None:
    try:
        return path.stat().st_mtime_ns
    except OSError:
        return None


def _digest(path: Path) -> str | None:
    """SHA-256 of a file's bytes, None where there is no file (or a folder)."""
    if not path.is_file():
        return None
    sha = hashlib.sha256()
    with path.open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            sha.update(block)
    return sha.hexdigest()


def _record_path(outputs: list[str], root: Path) -> Path:
    key = hashlib.sha256("\0".join(sorted(outputs)).encode()).hexdigest()[:32]
    return root / RECORDS / f"{key}.json"


def _write_json(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    tmp.write_text(json.dumps(data) + "\n", encoding="utf-8")
    os.replace(tmp, path)


def _finished(root: Path, outputs: list[str], record: Path, fingerprint: str | None) -> None:
    """A job ended well: what made its outputs (:data:`MADE`), then its record goes."""
    made = root / MADE / record.name
    if fingerprint is None:
        made.unlink(missing_ok=True)
    else:
        made_outputs = {o: [_digest(root / o), _mtime_ns(root / o)] for o in outputs}
        _write_json(made, {"params": fingerprint, "outputs": made_outputs})
    record.unlink(missing_ok=True)


def job_started(
    outputs: Iterable[str], root: str | os.PathLike[str] = ".", *, params: Any = None
) -> Path:
    """Record that the job writing ``outputs`` with ``params`` runs; the record goes when
    this process exits without an uncaught exception, leaving what made the outputs.
    Returns the record's path."""
    outputs = sorted(str(o) for o in outputs)
    root = Path(root)
    record = _record_path(outputs, root)
    fingerprint = params_fingerprint(params)
    _write_json(record, {"outputs": outputs, "params": fingerprint})
    failed = []
    previous = sys.excepthook

    def hook(kind, value, tb):
        failed.append(kind)
        previous(kind, value, tb)

    sys.excepthook = hook
    atexit.register(lambda: None if failed else _finished(root, outputs, record, fingerprint))
    return record


def _read_record(record: Path) -> dict[str, Any] | None:
    """A record of :func:`job_started` (or of the older list-only form), None if unreadable."""
    try:
        data = json.loads(record.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return {"outputs": data} if isinstance(data, list) else data


def _restored_as_made(root: Path, record: Path, data: Mapping[str, Any]) -> bool:
    """Whether every output of the unfinished job ``data`` holds what the last finished
    job of the same parameters wrote there; if so, each gets back the time stamp it was
    written with."""
    made_path = root / MADE / record.name
    if data.get("params") is None or not made_path.is_file():
        return False
    try:
        made = json.loads(made_path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    wrote = made.get("outputs") or {}
    same = made.get("params") == data["params"] and all(
        isinstance(wrote.get(o), list) and _digest(root / o) == wrote[o][0] for o in data["outputs"]
    )
    if same:
        for o in data["outputs"]:
            if wrote[o][1] is not None:
                os.utime(root / o, ns=(wrote[o][1], wrote[o][1]))
    return same


def mark_unfinished_outputs(root: str | os.PathLike[str] = ".") -> list[Path]:
    """Set the time stamp of every existing output named by a record of a job that did not
    finish to the epoch (so that Snakemake runs the job again); returns those files."""
    root = Path(root)
    folder = root / RECORDS
    marked = []
    for record in sorted(folder.glob("*.json")) if folder.is_dir() else []:
        data = _read_record(record)
        if data is None:
            continue
        if _restored_as_made(root, record, data):
            record.unlink(missing_ok=True)  # put back as a job of the same parameters made it
            continue
        for name in data["outputs"]:
            path = root / name
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
        data = _read_record(record)
        outputs = data["outputs"] if data else []
        if outputs and {os.path.normpath(o) for o in outputs} <= done:
            record.unlink(missing_ok=True)
            gone += 1
    return gone
