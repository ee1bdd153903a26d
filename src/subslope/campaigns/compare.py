"""Compare the outputs of two campaign runs: same numbers, dataset by dataset.

A refactoring of the package must not change what the campaign computes. Run the tiny
campaign before and after the change (same seed, machine and torch build), then::

    subslope compare-runs BASELINE/results results

It checks, under both ``results/`` folders:

- every HDF5 file (shards, profiles, HST profiles): the same datasets, bit-identical,
  and the same attributes except those that record the code layout or the config text
  (``--ignore-attr``);
- JSON files (whitening statistics, thresholds, trend) equal, but for the SHA-256 and
  size of the shard files they name;
- ``model.pt``: the same tensors (``torch.equal``), the same model card; read with
  ``weights_only=True``, so a model file that is not ours runs no code;
- ``.npz`` arrays bit-identical;
- CSV files cell by cell (``training_log.csv`` on its loss and lr columns, whose
  timing columns differ from run to run; ``stage_runtime.csv`` is skipped);
- ``summary.md``: every number outside the run-time table and the config hash.

Figures, Snakemake benchmark files, training checkpoints (whose folder name hashes the
config layout), the shard cache (keyed by the package's code digest) and ``run.json``
(machine and date) are not compared.
Prints one line per compared file and exits 1 when anything differs.
"""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import h5py
import numpy as np

__all__ = ["DEFAULT_IGNORED_ATTRS", "compare_file", "compare_trees", "summary_numbers"]

#: Attributes allowed to differ: they record the package version, the config text and
#: the render settings, whose layout a refactoring may change without changing a number.
DEFAULT_IGNORED_ATTRS = ("package_version", "config", "config_hash", "render_settings")
#: Files whose content is run-time or date dependent.
SKIPPED_SUFFIXES = (".pdf", ".png", ".tsv", ".log")
SKIPPED_NAMES = ("stage_runtime.csv", "run.json")
#: Folders not compared: checkpoints sit under a key that hashes the config layout
#: (``model.pt`` holds the final weights and is compared); shard-cache entries under a
#: key that digests the package's sources (the shards themselves are compared where the
#: campaign uses them).
SKIPPED_DIRS = ("checkpoints", "benchmarks", "shard_cache")
#: training_log.csv columns that are deterministic (the others hold wall times).
TRAINING_LOG_COLUMNS = ("epoch", "step", "train_loss", "val_loss", "lr")


def _h5_items(path: Path) -> dict[str, h5py.Dataset | h5py.Group]:
    items: dict[str, object] = {}
    with h5py.File(path, "r") as handle:
        handle.visititems(lambda name, obj: items.__setitem__(name, None))
    return items


def compare_h5(a: Path, b: Path, ignored_attrs: tuple[str, ...]) -> list[str]:
    """Differences between two HDF5 files: datasets bit for bit, attributes by value."""
    problems: list[str] = []
    with h5py.File(a, "r") as fa, h5py.File(b, "r") as fb:
        names_a: list[str] = []
        names_b: list[str] = []
        fa.visit(names_a.append)
        fb.visit(names_b.append)
        if sorted(names_a) != sorted(names_b):
            only_a = sorted(set(names_a) - set(names_b))
            only_b = sorted(set(names_b) - set(names_a))
            problems.append(f"members differ: only in baseline {only_a}, only in new {only_b}")
        for name in ["/"] + sorted(set(names_a) & set(names_b)):
            oa, ob = fa[name], fb[name]
            if isinstance(oa, h5py.Dataset):
                va, vb = oa[()], ob[()]
                if not _bit_equal(va, vb):
                    problems.append(f"dataset {name} differs")
            for key in sorted(set(oa.attrs) | set(ob.attrs)):
                if key in ignored_attrs:
                    continue
                if key not in oa.attrs or key not in ob.attrs:
                    problems.append(f"attribute {name}@{key} present in one file only")
                elif not _bit_equal(oa.attrs[key], ob.attrs[key]):
                    problems.append(f"attribute {name}@{key} differs")
    return problems


def _bit_equal(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    if a.dtype.kind in "fc":
        return a.tobytes() == b.tobytes()
    return bool(np.all(a == b))


#: JSON keys that record the bytes of another file (whose attributes may change).
FILE_DIGEST_KEYS = ("sha256", "bytes")


def _without_digests(obj):
    if isinstance(obj, dict):
        return {k: _without_digests(v) for k, v in obj.items() if k not in FILE_DIGEST_KEYS}
    if isinstance(obj, list):
        return [_without_digests(v) for v in obj]
    return obj


def compare_json(a: Path, b: Path) -> list[str]:
    """JSON files equal but for the digests of the files they name (whitening.json
    records each shard's SHA-256, which changes with a shard's attributes)."""
    ja = _without_digests(json.loads(a.read_text(encoding="utf-8")))
    jb = _without_digests(json.loads(b.read_text(encoding="utf-8")))
    return [] if ja == jb else ["JSON content differs"]


def compare_npz(a: Path, b: Path) -> list[str]:
    problems = []
    with np.load(a, allow_pickle=False) as za, np.load(b, allow_pickle=False) as zb:
        if sorted(za.files) != sorted(zb.files):
            problems.append(f"arrays differ: {sorted(za.files)} vs {sorted(zb.files)}")
        for key in sorted(set(za.files) & set(zb.files)):
            if not _bit_equal(za[key], zb[key]):
                problems.append(f"array {key} differs")
    return problems


def compare_model(a: Path, b: Path) -> list[str]:
    import torch

    try:
        ma = torch.load(a, map_location="cpu", weights_only=True)
        mb = torch.load(b, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises UnpicklingError, RuntimeError, EOFError, ...
        return [f"not a tensors-only model file ({type(exc).__name__}); not loaded"]
    problems = []
    sa, sb = _state_dict(ma), _state_dict(mb)
    if sorted(sa) != sorted(sb):
        problems.append("tensor names differ")
    for key in sorted(set(sa) & set(sb)):
        if not torch.equal(sa[key], sb[key]):
            problems.append(f"tensor {key} differs")
    return problems


def _state_dict(obj) -> dict:
    import torch

    if isinstance(obj, dict):
        for key in ("model_state", "state_dict", "model"):
            if key in obj and isinstance(obj[key], dict):
                return obj[key]
        return {k: v for k, v in obj.items() if isinstance(v, torch.Tensor)}
    return obj.state_dict()


def compare_csv(a: Path, b: Path) -> list[str]:
    ra = list(csv.DictReader(a.open(encoding="utf-8")))
    rb = list(csv.DictReader(b.open(encoding="utf-8")))
    if len(ra) != len(rb):
        return [f"{len(ra)} rows vs {len(rb)} rows"]
    columns = list(ra[0]) if ra else []
    if a.name == "training_log.csv":
        columns = [c for c in columns if c in TRAINING_LOG_COLUMNS]
    problems = []
    for i, (xa, xb) in enumerate(zip(ra, rb)):
        for col in columns:
            if xa.get(col) != xb.get(col):
                problems.append(f"row {i} column {col}: {xa.get(col)!r} vs {xb.get(col)!r}")
    return problems


_NUMBER = re.compile(r"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


def summary_numbers(text: str) -> list[str]:
    """Numbers of a summary.md outside its run-time section and config-hash line."""
    kept, skipping = [], False
    for line in text.splitlines():
        lowered = line.lower()
        if line.startswith("#"):
            skipping = "run time" in lowered or "runtime" in lowered
        if skipping or "config" in lowered or "generated" in lowered or "version" in lowered:
            continue
        kept.extend(_NUMBER.findall(line))
    return kept


def compare_summary(a: Path, b: Path) -> list[str]:
    na = summary_numbers(a.read_text(encoding="utf-8"))
    nb = summary_numbers(b.read_text(encoding="utf-8"))
    if na == nb:
        return []
    first = next((i for i, (x, y) in enumerate(zip(na, nb)) if x != y), min(len(na), len(nb)))
    return [
        f"numbers differ from the {first}-th on ({na[first : first + 3]} vs "
        f"{nb[first : first + 3]})"
    ]


def compare_file(a: Path, b: Path, ignored_attrs: tuple[str, ...]) -> list[str] | None:
    """Differences of one file pair, or None when the file kind is not compared."""
    if a.name in SKIPPED_NAMES or a.suffix in SKIPPED_SUFFIXES:
        return None
    if a.suffix in (".h5", ".hdf5"):
        return compare_h5(a, b, ignored_attrs)
    if a.suffix == ".json":
        return compare_json(a, b)
    if a.suffix == ".npz":
        return compare_npz(a, b)
    if a.suffix == ".pt":
        return compare_model(a, b)
    if a.suffix == ".csv":
        return compare_csv(a, b)
    if a.name == "summary.md":
        return compare_summary(a, b)
    return None


def compare_trees(base: Path, new: Path, ignored_attrs=DEFAULT_IGNORED_ATTRS) -> int:
    """Compare every file under two results folders; returns the number of differing files."""
    files_a = {p.relative_to(base) for p in base.rglob("*") if p.is_file()}
    files_b = {p.relative_to(new) for p in new.rglob("*") if p.is_file()}
    failed = 0
    files_a = {rel for rel in files_a if not set(rel.parts) & set(SKIPPED_DIRS)}
    files_b = {rel for rel in files_b if not set(rel.parts) & set(SKIPPED_DIRS)}
    for rel in sorted(files_a - files_b):
        if compare_file(base / rel, base / rel, ignored_attrs) is not None:
            print(f"MISSING  {rel}")
            failed += 1
    for rel in sorted(files_a & files_b):
        problems = compare_file(base / rel, new / rel, tuple(ignored_attrs))
        if problems is None:
            continue
        if problems:
            failed += 1
            print(f"DIFFERS  {rel}")
            for line in problems[:10]:
                print(f"         {line}")
        else:
            print(f"same     {rel}")
    for rel in sorted(files_b - files_a):
        print(f"new      {rel}")
    return failed
