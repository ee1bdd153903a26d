"""Checksummed data resources: the real HST cutouts, the empirical PSF, COSMOS sources.

The files the analysis reads are listed in ``subslope/data/registry.txt`` (relative path,
SHA-256, public URL). :func:`fetch` materialises them under a destination folder
(``resources/`` in the workflow), in the same layout (``hst/``, ``psf/``, ``cosmos/``):

1. from a local *mirror* folder with that layout, if it holds the file (copied, never
   linked, so the workflow's copy cannot change under it);
2. otherwise, if downloads are allowed and the file has a public URL, with ``pooch``
   (``known_hash`` set, so the download itself is verified).

Every file is written to a temporary name beside its destination, verified against the
registry checksum and only then renamed into place (atomic on POSIX), so a failure never
leaves a half-written or unverified file at the destination. Every fetched file gets the
same fixed time stamp (:data:`FETCHED_MTIME`): a file is its checksum, so fetching the
same bytes again must not look newer than the results made from them (Snakemake reruns
the jobs whose inputs are newer than their outputs). ``hst/catalog.csv`` was
compiled for this project and has no upstream URL: it is mirror-only.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import tempfile
from dataclasses import dataclass
from importlib import resources as importlib_resources
from pathlib import Path

__all__ = [
    "ResourceError",
    "ChecksumError",
    "MissingResourceError",
    "RegistryEntry",
    "load_registry",
    "sha256sum",
    "verify",
    "fetch",
    "fetch_files",
    "verify_files",
    "restore_deleted",
    "FETCHED_RECORDS",
    "FETCHED_MTIME",
]

log = logging.getLogger(__name__)


class ResourceError(ValueError):
    """A data resource could not be provided."""


class ChecksumError(ResourceError):
    """A file's SHA-256 differs from the one recorded in the registry."""


class MissingResourceError(ResourceError, FileNotFoundError):
    """A file is neither in the mirror nor downloadable."""


@dataclass(frozen=True)
class RegistryEntry:
    """One registered data file.

    Attributes
    ----------
    path: path relative to the resources folder, e.g. ``"hst/catalog.csv"``.
    sha256: expected SHA-256 (lower-case hex).
    url: public URL, or ``None`` for mirror-only files.
    """

    path: str
    sha256: str
    url: str | None


def load_registry(path: str | os.PathLike[str] | None = None) -> list[RegistryEntry]:
    """Read the registry (default: the one shipped in the package), in file order."""
    if path is None:
        text = (importlib_resources.files("subslope") / "data" / "registry.txt").read_text("utf-8")
        source = "subslope/data/registry.txt"
    else:
        text = Path(path).read_text("utf-8")
        source = str(path)
    entries: list[RegistryEntry] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 3 or len(parts[1]) != 64:
            raise ResourceError(
                f"{source}, line {lineno}: expected 'path sha256 url', got {line!r}"
            )
        rel, digest, url = parts
        entries.append(RegistryEntry(rel, digest.lower(), None if url == "-" else url))
    return entries


def sha256sum(path: str | os.PathLike[str]) -> str:
    """SHA-256 of a file, lower-case hex."""
    with open(path, "rb") as handle:
        return hashlib.file_digest(handle, "sha256").hexdigest()


def verify(path: str | os.PathLike[str], expected: str, *, name: str | None = None) -> None:
    """Raise :class:`ChecksumError` unless ``path`` has SHA-256 ``expected``."""
    actual = sha256sum(path)
    if actual != expected.lower():
        raise ChecksumError(
            f"checksum mismatch for {name or path}: expected sha256 {expected}, got {actual} "
            f"(file {path})"
        )


#: Modification time given to every fetched file (2000-01-01 UTC, seconds since the epoch).
FETCHED_MTIME = 946_684_800


def _default_mode() -> int:
    """Permissions of an ordinary new file under the current umask (mkstemp uses 0600)."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def _install(tmp: Path, dest: Path, entry: RegistryEntry, origin: str) -> None:
    """Verify ``tmp`` and rename it to ``dest``; ``tmp`` is removed on failure."""
    try:
        verify(tmp, entry.sha256, name=f"{entry.path} from {origin}")
        os.chmod(tmp, _default_mode())
        os.utime(tmp, (FETCHED_MTIME, FETCHED_MTIME))
        os.replace(tmp, dest)
    finally:
        tmp.unlink(missing_ok=True)


def _copy_from_mirror(src: Path, dest: Path, entry: RegistryEntry) -> None:
    fd, tmp_name = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".part", dir=dest.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        shutil.copyfile(src, tmp)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _install(tmp, dest, entry, origin=f"mirror {src}")


def _download(entry: RegistryEntry, dest: Path) -> None:
    import pooch

    tmpdir = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", suffix=".download", dir=dest.parent))
    try:
        try:
            got = pooch.retrieve(
                entry.url,
                known_hash=f"sha256:{entry.sha256}",
                fname=dest.name,
                path=tmpdir,
                progressbar=False,
            )
        except ValueError as exc:  # pooch's hash mismatch
            raise ChecksumError(
                f"download of {entry.path} from {entry.url} failed verification: {exc}"
            ) from exc
        except Exception as exc:  # network errors and HTTP errors
            raise MissingResourceError(
                f"could not download {entry.path} from {entry.url}: {exc}"
            ) from exc
        _install(Path(got), dest, entry, origin=entry.url)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)


def fetch(
    dest: str | os.PathLike[str],
    *,
    mirror: str | os.PathLike[str] | None = None,
    allow_download: bool = False,
    entries: list[RegistryEntry] | None = None,
) -> list[Path]:
    """Materialise the registered files under ``dest`` and return their paths.

    Parameters
    ----------
    dest:
        Destination folder (created if needed); files keep their registry layout.
    mirror:
        Local folder with the same layout; tried first. ``None`` or a missing folder means
        "no mirror".
    allow_download:
        Download files that the mirror lacks from their public URL.
    entries:
        Subset of the registry to fetch (default: all of it).

    A destination file whose checksum already matches is kept; one that does not is
    removed and fetched again. Raises
    :class:`ChecksumError` (naming the file, the expected and the actual SHA-256) or
    :class:`MissingResourceError`; no partial file is left at the destination either way.
    """
    dest = Path(dest)
    mirror_dir = Path(mirror) if mirror is not None else None
    if mirror_dir is not None and not mirror_dir.is_dir():
        log.warning("data mirror %s does not exist; ignoring it", mirror_dir)
        mirror_dir = None
    entries = load_registry() if entries is None else entries
    done: list[Path] = []
    for entry in entries:
        target = dest / entry.path
        target.parent.mkdir(parents=True, exist_ok=True)
        if target.is_file():
            if sha256sum(target) == entry.sha256:
                log.info("%s: present and verified", entry.path)
                _mark_fetched(dest, entry)
                done.append(target)
                continue
            log.warning("%s: present but checksum differs; replacing it", entry.path)
            target.unlink()
        src = mirror_dir / entry.path if mirror_dir is not None else None
        if mirror_dir is not None:
            where = f"mirror {mirror_dir}"
        elif mirror is None:
            where = "any mirror (none configured)"
        else:
            where = f"mirror {mirror} (not a folder)"
        if src is not None and src.is_file():
            log.info("%s: copying from mirror %s", entry.path, mirror_dir)
            _copy_from_mirror(src, target, entry)
        elif allow_download and entry.url is not None:
            log.info("%s: downloading %s", entry.path, entry.url)
            try:
                _download(entry, target)
            except MissingResourceError as exc:
                raise MissingResourceError(
                    f"data file {entry.path} not found in {where}, and {exc}"
                ) from exc
        else:
            if entry.url is None:
                how = "it is mirror-only (no public URL)"
            elif not allow_download:
                how = "downloads are not allowed (data.allow_download: false)"
            else:
                how = "no URL"
            raise MissingResourceError(
                f"data file {entry.path} not found in {where} and {how}; set data.mirror "
                f"or the SUBSLOPE_DATA_MIRROR environment variable to a folder that holds it"
            )
        _mark_fetched(dest, entry)
        done.append(target)
    return done


#: Folder (inside the resources folder) of the records of fetched files.
FETCHED_RECORDS = ".fetched"


def _mark_fetched(dest: Path, entry: RegistryEntry) -> None:
    """Record that ``entry`` was fetched into ``dest`` (its checksum, in
    ``dest/.fetched/<path>.sha256``): :func:`restore_deleted` puts such a file back."""
    from subslope.io.atomic import write_text

    record = dest / FETCHED_RECORDS / f"{entry.path}.sha256"
    if not record.is_file() or record.read_text(encoding="utf-8").strip() != entry.sha256:
        write_text(record, entry.sha256 + "\n")


def restore_deleted(
    dest: str | os.PathLike[str], *, mirror: str | os.PathLike[str] | None
) -> list[Path]:
    """Put back, from ``mirror``, every registered file that was fetched into ``dest``
    before (it has a record) and is missing now; returns the restored paths.

    The workflow calls this before it builds its graph: a restored file has the checksum
    of the registry and the time stamp of its first fetch (its record's), so the jobs
    that read it see the file they read before and do not run again (a file fetched by a
    job instead would make every reader run again). Files the mirror lacks are left to
    rule fetch_data."""
    dest = Path(dest)
    mirror_dir = Path(mirror) if mirror is not None else None
    restored = []
    for entry in load_registry():
        target = dest / entry.path
        record = dest / FETCHED_RECORDS / f"{entry.path}.sha256"
        if target.is_file():
            if not record.is_file():  # fetched before the records were kept
                _mark_fetched(dest, entry)
                when = target.stat().st_mtime
                os.utime(record, (when, when))
            continue
        src = mirror_dir / entry.path if mirror_dir is not None else None
        if not record.is_file() or src is None or not src.is_file():
            continue
        if record.read_text(encoding="utf-8").strip() != entry.sha256:
            continue  # the registry changed since: a new file, fetched by its job
        target.parent.mkdir(parents=True, exist_ok=True)
        _copy_from_mirror(src, target, entry)
        # the time of the first fetch: older than every reader's outputs, newer than the
        # fetch script (Snakemake reruns a script rule whose script is newer than its output)
        when = record.stat().st_mtime
        os.utime(target, (when, when))
        restored.append(target)
    return restored


def fetch_files(
    files: list[str | os.PathLike[str]],
    *,
    mirror: str | os.PathLike[str] | None = None,
    allow_download: bool = False,
) -> list[Path]:
    """Fetch the given destination files, each of which must end with a registry path.

    ``resources/psf/emp_psf_f814w.fits`` means registry entry ``psf/emp_psf_f814w.fits``
    under the folder ``resources``. This is the form the workflow uses (its outputs are
    the files themselves). Raises :class:`ResourceError` for a file that is not
    registered.
    """
    registry = load_registry()
    groups: dict[Path, list[RegistryEntry]] = {}
    for file in files:
        posix = Path(file).as_posix()
        matches = [e for e in registry if posix == e.path or posix.endswith("/" + e.path)]
        if not matches:
            raise ResourceError(
                f"{file} is not a registered data file (see subslope/data/registry.txt)"
            )
        entry = max(matches, key=lambda e: len(e.path))
        root = Path(posix[: len(posix) - len(entry.path)] or ".")
        groups.setdefault(root, []).append(entry)
    out: list[Path] = []
    for root, entries in groups.items():
        out += fetch(root, mirror=mirror, allow_download=allow_download, entries=entries)
    return out


def verify_files(files) -> int:
    """Verify the registered data files among ``files`` against the registry (one hash
    each, cheap next to any job that reads them) and return how many were checked.

    A job calls this before it reads its resources, so a file changed after
    ``fetch_data`` is refused, naming it and how to recover, instead of being used.
    Files that are not registered (the full COSMOS catalogue put in place by hand) are
    left alone."""
    registry = load_registry()
    checked = 0
    for file in files:
        posix = Path(file).as_posix()
        matches = [e for e in registry if posix == e.path or posix.endswith("/" + e.path)]
        if not matches:
            continue
        entry = max(matches, key=lambda e: len(e.path))
        if not Path(file).is_file():
            raise MissingResourceError(
                f"data file {file} is missing; run snakemake again to fetch it"
            )
        actual = sha256sum(file)
        if actual != entry.sha256:
            raise ChecksumError(
                f"data file {file} changed after it was fetched: sha256 {actual}, the registry "
                f"has {entry.sha256}; delete it and run snakemake again to fetch it"
            )
        checked += 1
    return checked
