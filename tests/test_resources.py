"""Data resources: registry, mirror copy, checksum verification, atomicity."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import pytest

from subslope.cli import main as cli_main
from subslope.io import resources as res


def _entry(rel: str, content: bytes, url: str | None = None) -> res.RegistryEntry:
    return res.RegistryEntry(rel, hashlib.sha256(content).hexdigest(), url)


def _leftovers(folder: Path) -> list[Path]:
    """Temporary files (.part, .download) anywhere under folder (the records of fetched
    files, res.FETCHED_RECORDS, are not temporary)."""
    return [
        p
        for p in folder.rglob("*")
        if p.name.startswith(".") and res.FETCHED_RECORDS not in p.relative_to(folder).parts
    ]


def test_registry_lists_the_real_data():
    reg = res.load_registry()
    paths = [e.path for e in reg]
    assert len(paths) == len(set(paths)) == 21
    assert sum(p.startswith("hst/") and p.endswith(".npy") for p in paths) == 13
    assert "psf/emp_psf_f814w.fits" in paths
    assert sum(p.startswith("cosmos/") for p in paths) == 3
    assert sum(p.startswith("cosmos_extension/") for p in paths) == 3
    by_path = {e.path: e for e in reg}
    assert by_path["hst/catalog.csv"].url is None  # compiled for this project: mirror-only
    assert all(
        e.url and e.url.startswith("https://raw.githubusercontent.com/")
        for e in reg
        if e.path != "hst/catalog.csv"
    )
    assert by_path["psf/emp_psf_f814w.fits"].url.endswith(
        "paltas/main/datasets/hst_psf/emp_psf_f814w.fits"
    )
    ext = by_path["cosmos_extension/real_galaxy_images_extension.fits"].url
    assert "LSSTDESC/BlendingToolKit/90f1d531dc3db74d0fd6852fb6e82d457f062899/data/cosmos/" in ext


def test_registry_matches_mirror_checksums(data_dir):
    """The registry sums equal the mirror's SHA256SUMS (and the files themselves)."""
    sums = dict(
        reversed(line.split())
        for line in (data_dir / "SHA256SUMS").read_text().splitlines()
        if line.strip()
    )
    for entry in res.load_registry():
        if entry.path in sums:
            assert sums[entry.path] == entry.sha256, entry.path
        assert res.sha256sum(data_dir / entry.path) == entry.sha256, entry.path


def test_fetch_from_real_mirror(data_dir, tmp_path):
    dest = tmp_path / "resources"
    files = res.fetch(dest, mirror=data_dir)
    assert len(files) == 21 and all(f.is_file() and not f.is_symlink() for f in files)
    assert (dest / "hst" / "SDSSJ0946+1006_npix100.npy").is_file()
    assert not _leftovers(dest)
    # Second call: everything present and verified, nothing rewritten.
    mtimes = {f: f.stat().st_mtime_ns for f in files}
    assert res.fetch(dest, mirror=None) == files
    assert {f: f.stat().st_mtime_ns for f in files} == mtimes


def test_fetch_files_maps_outputs_to_registry(data_dir, tmp_path):
    want = [tmp_path / "r" / "hst" / "catalog.csv", tmp_path / "r" / "psf" / "emp_psf_f814w.fits"]
    assert res.fetch_files(want, mirror=data_dir) == want
    with pytest.raises(res.ResourceError, match="not a registered data file"):
        res.fetch_files([tmp_path / "r" / "hst" / "other.npy"], mirror=data_dir)


def test_checksum_mismatch_names_file_and_sums_and_leaves_nothing(tmp_path):
    mirror, dest = tmp_path / "mirror", tmp_path / "dest"
    (mirror / "hst").mkdir(parents=True)
    (mirror / "hst" / "a.npy").write_bytes(b"corrupted")
    entry = _entry("hst/a.npy", b"original")
    with pytest.raises(res.ChecksumError) as info:
        res.fetch(dest, mirror=mirror, entries=[entry])
    msg = str(info.value)
    assert (
        "hst/a.npy" in msg
        and entry.sha256 in msg
        and hashlib.sha256(b"corrupted").hexdigest() in msg
    )
    assert not (dest / "hst" / "a.npy").exists()
    assert not _leftovers(dest)
    assert isinstance(info.value, ValueError)


def test_corrupt_destination_is_replaced(tmp_path):
    mirror, dest = tmp_path / "mirror", tmp_path / "dest"
    (mirror / "psf").mkdir(parents=True)
    (mirror / "psf" / "p.fits").write_bytes(b"good")
    (dest / "psf").mkdir(parents=True)
    (dest / "psf" / "p.fits").write_bytes(b"stale")
    entry = _entry("psf/p.fits", b"good")
    res.fetch(dest, mirror=mirror, entries=[entry])
    assert (dest / "psf" / "p.fits").read_bytes() == b"good"


def test_missing_file_without_download(tmp_path):
    mirror = tmp_path / "mirror"
    mirror.mkdir()
    entry = _entry("hst/a.npy", b"x", url="https://example.invalid/a.npy")
    with pytest.raises(res.MissingResourceError, match=r"hst/a\.npy.*downloads are not allowed"):
        res.fetch(tmp_path / "dest", mirror=mirror, entries=[entry])
    mirror_only = _entry("hst/catalog.csv", b"x")
    with pytest.raises(res.MissingResourceError, match="mirror-only"):
        res.fetch(
            tmp_path / "dest",
            mirror=tmp_path / "nowhere",
            allow_download=True,
            entries=[mirror_only],
        )
    assert not _leftovers(tmp_path / "dest")


def test_download_path_verifies_and_is_atomic(tmp_path, monkeypatch):
    """pooch.retrieve is replaced by a fake (no network in tests); good and bad payloads."""
    import pooch

    payload = {"bytes": b"payload"}
    calls = []

    def fake_retrieve(url, known_hash, fname, path, progressbar):
        calls.append((url, known_hash))
        out = Path(path) / fname
        out.write_bytes(payload["bytes"])
        expected = known_hash.split(":", 1)[1]
        if hashlib.sha256(payload["bytes"]).hexdigest() != expected:
            out.unlink()
            raise ValueError(
                f"SHA256 hash of downloaded file does not match the known hash: expected {expected}"
            )
        return str(out)

    monkeypatch.setattr(pooch, "retrieve", fake_retrieve)
    entry = _entry("cosmos/g.fits", b"payload", url="https://example.invalid/g.fits")
    dest = tmp_path / "dest"
    res.fetch(dest, mirror=None, allow_download=True, entries=[entry])
    assert (dest / "cosmos" / "g.fits").read_bytes() == b"payload"
    assert calls == [("https://example.invalid/g.fits", f"sha256:{entry.sha256}")]
    assert not _leftovers(dest)

    (dest / "cosmos" / "g.fits").unlink()
    payload["bytes"] = b"tampered"
    with pytest.raises(res.ChecksumError, match=r"cosmos/g\.fits"):
        res.fetch(dest, mirror=None, allow_download=True, entries=[entry])
    assert not (dest / "cosmos" / "g.fits").exists()
    assert not _leftovers(dest)


def test_cli_fetch_data(data_dir, tmp_path, capsys):
    assert cli_main(["fetch-data", "--mirror", str(data_dir), "--dest", str(tmp_path / "r")]) == 0
    assert (tmp_path / "r" / "hst" / "catalog.csv").is_file()
    assert (
        cli_main(["fetch-data", "--mirror", str(tmp_path / "none"), "--dest", str(tmp_path / "s")])
        == 1
    )
    assert "not found" in capsys.readouterr().err


def test_a_fetched_file_deleted_later_is_restored_with_its_stamp(data_dir, tmp_path):
    from subslope.io.resources import FETCHED_RECORDS, restore_deleted

    entries = [e for e in res.load_registry() if e.path.startswith("psf/")]
    [psf] = res.fetch(tmp_path, mirror=data_dir, entries=entries)
    assert (tmp_path / FETCHED_RECORDS / "psf" / "emp_psf_f814w.fits.sha256").is_file()
    assert restore_deleted(tmp_path, mirror=data_dir) == []  # nothing missing
    psf.unlink()
    assert restore_deleted(tmp_path, mirror=tmp_path / "nowhere") == []  # left to the job
    record = tmp_path / FETCHED_RECORDS / "psf" / "emp_psf_f814w.fits.sha256"
    os.utime(record, (1.5e9, 1.5e9))
    assert restore_deleted(tmp_path, mirror=data_dir) == [psf]
    # the time stamp of the first fetch (the record's), the registry's bytes
    assert psf.stat().st_mtime == 1.5e9 and res.sha256sum(psf) == entries[0].sha256
    # a file never fetched here (no record) is not fetched by the restore
    assert not (tmp_path / "hst").exists()
    # a record of other bytes (the registry changed since): the new file is the job's
    psf.unlink()
    (tmp_path / FETCHED_RECORDS / "psf" / "emp_psf_f814w.fits.sha256").write_text("0" * 64)
    assert restore_deleted(tmp_path, mirror=data_dir) == []
