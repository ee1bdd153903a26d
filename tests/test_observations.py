"""Real HST cutouts and catalogue: loading, and clear errors for bad input."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from subslope.io.observations import (
    IMAGE_SHAPE,
    Observation,
    ObservationError,
    load_catalog,
    load_hst,
    load_image,
)

HEADER = "file,system,z_lens,z_source,theta_E_arcsec\n"


def test_load_real_hst(data_dir):
    obs = load_hst(data_dir / "hst")
    assert len(obs) == 13
    assert all(isinstance(o, Observation) for o in obs)
    names = [o.name for o in obs]
    assert len(set(names)) == 13
    assert all(
        n.startswith("SDSSJ") and len(n) == 14 for n in names
    )  # SDSS names, not plate-MJD-fibre
    assert "SDSSJ0946+1006" in names
    # Ordered as the catalogue.
    assert names == [row["system"] for row in load_catalog(data_dir / "hst" / "catalog.csv")]
    by_name = {o.name: o for o in obs}
    # Catalogue join: a plate-MJD-fibre file is mapped to its SDSS name.
    j1627 = by_name["SDSSJ1627-0053"]
    assert j1627.file.name == "GAL-0364-52000-084_npix100.npy"
    assert (j1627.z_lens, j1627.z_source, j1627.theta_e) == (0.208, 0.524, 1.23)
    for o in obs:
        assert o.image.shape == IMAGE_SHAPE
        assert o.image.dtype == np.float64 and o.image.dtype.isnative
        assert np.isfinite(o.image).all()
        assert not o.image.flags.writeable
        # e-/s per pixel: the lens peak is a few to ~10 e-/s near the centre.
        assert 1.0 < o.image.max() < 100.0
        j, i = np.unravel_index(np.argmax(o.image), o.image.shape)
        assert abs(j - 49.5) < 15 and abs(i - 49.5) < 15
        assert 0 < o.z_lens < o.z_source and o.theta_e > 0


def test_npy_matches_raw_bytes(data_dir):
    path = data_dir / "hst" / "SDSSJ0946+1006_npix100.npy"
    raw = np.load(path)
    assert raw.dtype == np.dtype(">f4")  # big-endian as shipped
    np.testing.assert_array_equal(load_image(path), raw.astype(np.float64))


def test_fits_image(tmp_path, rng):
    from astropy.io import fits

    data = rng.normal(size=IMAGE_SHAPE).astype(">f4")
    hdus = fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(data)])  # empty primary, image in HDU 1
    hdus.writeto(tmp_path / "x.fits")
    np.testing.assert_array_equal(load_image(tmp_path / "x.fits"), data.astype(np.float64))
    fits.HDUList([fits.PrimaryHDU()]).writeto(tmp_path / "empty.fits")
    with pytest.raises(ObservationError, match=r"empty\.fits: no HDU with 2-D image"):
        load_image(tmp_path / "empty.fits")


@pytest.mark.parametrize(
    "array, match",
    [
        (np.zeros((100, 99), dtype=">f4"), r"shape \(100, 99\), expected \(100, 100\)"),
        (np.zeros((100,), dtype=">f4"), r"shape \(100,\)"),
        (np.where(np.eye(100, dtype=bool), np.nan, 0.0), r"non-finite pixel.*row 0, column 0"),
        (np.full((100, 100), np.inf), "non-finite"),
        (np.array(["a"] * 10000).reshape(100, 100), "numeric"),
    ],
)
def test_bad_images(tmp_path, array, match):
    path = tmp_path / "bad_npix100.npy"
    np.save(path, array)
    with pytest.raises(ObservationError, match=match) as info:
        load_image(path)
    assert "bad_npix100.npy" in str(info.value)


def test_unreadable_and_unknown_files(tmp_path):
    (tmp_path / "junk.npy").write_bytes(b"not a numpy file")
    with pytest.raises(ObservationError, match=r"junk\.npy: cannot read"):
        load_image(tmp_path / "junk.npy")
    (tmp_path / "a.png").write_bytes(b"")
    with pytest.raises(ObservationError, match="unknown image format"):
        load_image(tmp_path / "a.png")
    with pytest.raises(ObservationError, match="not found"):
        load_image(tmp_path / "missing.npy")


def _folder(tmp_path, data_dir, catalog_text):
    folder = tmp_path / "hst"
    folder.mkdir()
    shutil.copy(data_dir / "hst" / "SDSSJ0946+1006_npix100.npy", folder)
    shutil.copy(data_dir / "hst" / "SDSSJ0946+1006_npix100.npy", folder / "copy_npix100.npy")
    (folder / "catalog.csv").write_text(HEADER + catalog_text)
    return folder


@pytest.mark.parametrize(
    "rows, match",
    [
        (
            "SDSSJ0000+0000_npix100.npy,SDSSJ0000+0000,0.2,0.6,1.0\n",
            r"SDSSJ0000\+0000 lists file .* not found",
        ),
        (
            "SDSSJ0946+1006_npix100.npy,SDSSJ0946+1006,0.222,0.609,1.38\n"
            "copy_npix100.npy,SDSSJ0946+1006,0.222,0.609,1.38\n",
            r"line 3: duplicate system 'SDSSJ0946\+1006' \(also on line 2\)",
        ),
        (
            "SDSSJ0946+1006_npix100.npy,A,0.222,0.609,1.38\nSDSSJ0946+1006_npix100.npy,B,0.222,0.609,1.38\n",
            "line 3: duplicate file",
        ),
        (
            "SDSSJ0946+1006_npix100.npy,X,abc,0.609,1.38\n",
            r"line 2: column 'z_lens' = 'abc' is not a number",
        ),
        (
            "SDSSJ0946+1006_npix100.npy,X,0.7,0.6,1.38\n",
            r"line 2 \(X\): need 0 < z_lens < z_source",
        ),
        ("SDSSJ0946+1006_npix100.npy,X,0.2,0.6,-1\n", "theta_E_arcsec must be > 0"),
        (",X,0.2,0.6,1\n", "line 2: empty 'file'"),
        ("/etc/passwd,X,0.2,0.6,1\n", r"line 2 \(X\): file '/etc/passwd' must be a path inside"),
        ("../hst/copy_npix100.npy,X,0.2,0.6,1\n", r"file '\.\./hst/copy_npix100.npy' must be"),
        ("", "no rows"),
    ],
)
def test_bad_catalogue(tmp_path, data_dir, rows, match):
    folder = _folder(tmp_path, data_dir, rows)
    with pytest.raises(ObservationError, match=match) as info:
        load_hst(folder)
    assert "catalog.csv" in str(info.value)


def test_catalogue_missing_column(tmp_path):
    (tmp_path / "catalog.csv").write_text("file,system,z_lens\nA.npy,A,0.2\n")
    with pytest.raises(
        ObservationError, match=r"missing column\(s\) \['z_source', 'theta_E_arcsec'\]"
    ):
        load_catalog(tmp_path / "catalog.csv")
    with pytest.raises(ObservationError, match="catalogue not found"):
        load_catalog(tmp_path / "nope.csv")
