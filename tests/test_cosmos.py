"""COSMOS real-galaxy catalogue: loading, cuts, splits and placement at z_source."""

import numpy as np
import pytest
from astropy.cosmology import Planck18

from subslope.io.cosmos import (
    CosmosCatalog,
    CosmosCuts,
    CosmosError,
    normalize_to_magnitude,
    place_at_redshift,
    split_idents,
)


@pytest.fixture
def catalog(data_dir):
    return CosmosCatalog.load(data_dir / "cosmos")


def test_loads_the_bundled_galaxies(catalog):
    assert len(catalog) == 10
    assert catalog.idents[0] == 141190
    t = catalog.table
    np.testing.assert_allclose(t["pixel_scale"], 0.03, rtol=1e-6)
    stamp = catalog.stamp(141190)
    assert stamp.shape == (t.loc[0, "ny"], t.loc[0, "nx"]) == (234, 233)
    assert np.isfinite(stamp).all() and stamp.sum() > 0


def test_paper_cuts_reject_all_bundled_galaxies_with_a_clear_error(catalog):
    # The ten bundled galaxies are fainter (mag 21-23.3) than the paper's mag_auto < 20 cut.
    with pytest.raises(CosmosError, match="mag_auto 21.04"):
        catalog.select(CosmosCuts())


def test_relaxed_cuts(catalog):
    sel = catalog.select(
        CosmosCuts(
            mag_max=None, min_stamp_side=64, min_flux_radius=10.0, zphot_max=1.0, exclude=(178249,)
        )
    )
    t = sel.table
    assert len(sel) > 0
    assert (np.minimum(t["nx"], t["ny"]) >= 64).all() and (t["flux_radius"] > 10).all()
    assert (t["zphot"] < 1).all() and 178249 not in t["ident"].tolist()


def test_split_is_deterministic_disjoint_and_complete(catalog):
    fractions = {"train": 0.8, "validation": 0.1, "test": 0.1}
    a = split_idents(catalog.idents, fractions)
    b = split_idents(catalog.idents[::-1], fractions)
    for s in a:
        np.testing.assert_array_equal(a[s], b[s])
    union = np.concatenate(list(a.values()))
    assert len(union) == len(set(union)) == 10
    assert len(a["validation"]) >= 1 and len(a["test"]) >= 1
    c = split_idents(catalog.idents, fractions, salt="other")
    assert any(not np.array_equal(a[s], c[s]) for s in a)


def test_split_rejects_bad_fractions():
    with pytest.raises(CosmosError, match="sum to 1"):
        split_idents([1, 2, 3], {"train": 0.5, "test": 0.2})
    with pytest.raises(CosmosError, match="unknown split"):
        split_idents([1, 2, 3], {"training": 1.0})


def test_place_at_redshift_flux_and_size(catalog):
    stamp = catalog.stamp(141190)
    z_phot, z_s = 0.19499999, 0.6
    sb, scale = place_at_redshift(stamp, 0.03, z_phot, z_s)
    ratio = (
        Planck18.angular_diameter_distance(z_phot) / Planck18.angular_diameter_distance(z_s)
    ).value
    assert scale == pytest.approx(0.03 * ratio, rel=1e-12)
    assert scale < 0.03  # a galaxy moved further away looks smaller
    zp = 10 ** ((25.127 - 25.95) / 2.5)
    k_corr = 10 ** (-(2.5 * np.log(1 + z_s) - 2.5 * np.log(1 + z_phot)) / 2.5)
    expected_flux = stamp.sum() * zp * k_corr * ratio**2
    assert np.sum(sb) * scale**2 == pytest.approx(expected_flux, rel=1e-12)


def test_normalize_to_magnitude():
    sb = np.ones((10, 10))
    out = normalize_to_magnitude(sb, 0.01, 21.0)
    assert np.sum(out) * 0.01**2 == pytest.approx(10 ** (-0.4 * (21.0 - 25.127)))
    with pytest.raises(CosmosError, match="total flux"):
        normalize_to_magnitude(np.zeros((3, 3)), 0.01, 21.0)


def test_missing_files_are_named(tmp_path, data_dir):
    with pytest.raises(CosmosError, match="real_galaxy_catalog_23.5.fits"):
        CosmosCatalog.load(tmp_path)
    for name in ("real_galaxy_catalog_23.5.fits", "real_galaxy_catalog_23.5_fits.fits"):
        (tmp_path / name).write_bytes((data_dir / "cosmos" / name).read_bytes())
    with pytest.raises(CosmosError, match="image file not found"):
        CosmosCatalog.load(tmp_path)
