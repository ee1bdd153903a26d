"""COSMOS real-galaxy catalogue: loading, cuts, splits and placement at z_source."""

import numpy as np
import pytest
from astropy.cosmology import Planck18

from subslope.io.cosmos import (
    CosmosCatalog,
    CosmosCuts,
    CosmosError,
    clean_stamp,
    denoise_stamp,
    normalize_to_magnitude,
    place_at_redshift,
    residual_noise_ratio,
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
    with pytest.raises(CosmosError, match=r"exactly one real_galaxy_catalog_\*.fits.*none"):
        CosmosCatalog.load(tmp_path)
    with pytest.raises(CosmosError, match="real_galaxy_catalog_23.5.fits"):
        CosmosCatalog.load(tmp_path, "real_galaxy_catalog_23.5.fits")
    for name in ("real_galaxy_catalog_23.5.fits", "real_galaxy_catalog_23.5_fits.fits"):
        (tmp_path / name).write_bytes((data_dir / "cosmos" / name).read_bytes())
    with pytest.raises(CosmosError, match="image file not found"):
        CosmosCatalog.load(tmp_path)


def test_several_folders_read_together_with_the_extension_columns(data_dir):
    both = CosmosCatalog.load([data_dir / "cosmos", data_dir / "cosmos_extension"])
    assert len(both) == 110
    ext = both.table.iloc[10:]
    # the extension's fit table has ZPHOT (upper case) and no mag_auto: MAG stands in
    assert ext["zphot"].between(0, 6).all() and ext["mag_auto"].between(18, 30).all()
    assert set(both.table["folder"]) == {
        str(data_dir / "cosmos"),
        str(data_dir / "cosmos_extension"),
    }
    ident = int(ext["ident"].iloc[0])
    assert both.stamp(ident).shape == (int(ext["ny"].iloc[0]), int(ext["nx"].iloc[0]))
    assert both.noise_sigma(ident) == pytest.approx(np.sqrt(ext["noise_variance"].iloc[0]))


def test_duplicate_idents_over_folders_are_refused(data_dir):
    with pytest.raises(CosmosError, match="duplicate IDENT"):
        CosmosCatalog.load([data_dir / "cosmos", data_dir / "cosmos"])


def _blob(n=64, sigma=0.05, seed=1):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:n, :n] - (n - 1) / 2
    galaxy = np.exp(-0.5 * (xx**2 + yy**2) / 4.0**2)
    return galaxy, galaxy + rng.normal(0, sigma, (n, n))


def test_cleaning_keeps_the_central_galaxy_and_zeroes_the_sky():
    galaxy, stamp = _blob()
    stamp[5:9, 5:9] += 3.0  # a neighbour in the corner
    out = clean_stamp(stamp, 0.05, threshold=3.0, smoothing=1.0, dilate=2, taper=2.0)
    assert out.peak_snr == pytest.approx(stamp.max() / 0.05)
    assert np.all(out.image[5:9, 5:9] == 0)  # not connected to the centre
    assert np.all((out.weight >= 0) & (out.weight <= 1))
    assert 0.02 < out.footprint_fraction < 0.2
    # the flux of the galaxy is kept to a few per cent; the sky outside is exactly zero
    assert out.image.sum() == pytest.approx(galaxy.sum(), rel=0.05)
    far = np.hypot(*(np.mgrid[:64, :64] - 31.5)) > 20
    assert np.all(out.image[far] == 0)


def test_cleaning_edge_cases():
    galaxy, stamp = _blob()
    hard = clean_stamp(stamp, 0.05, taper=0.0, dilate=0, smoothing=0.0)
    assert set(np.unique(hard.weight)) <= {0.0, 1.0}
    empty = clean_stamp(np.zeros((16, 16)), 1.0)
    assert empty.footprint_fraction == 0.0 and np.all(empty.image == 0)
    off_centre = np.zeros((32, 32))
    off_centre[10:13, 10:13] = 10.0
    assert clean_stamp(off_centre, 0.1).image[11, 11] > 0  # nearest bright region kept
    with pytest.raises(CosmosError, match="noise sigma"):
        clean_stamp(stamp, 0.0)


def test_cleaning_the_bundled_stamps_keeps_their_flux(data_dir):
    cat = CosmosCatalog.load(data_dir / "cosmos")
    for ident, mag in zip(cat.idents, cat.table["mag_auto"], strict=True):
        out = clean_stamp(cat.stamp(ident), cat.noise_sigma(ident))
        assert np.all(np.isfinite(out.image))
        assert 0.03 < out.footprint_fraction < 0.8
        # the footprint holds the galaxy's catalogue flux (mag_auto): within 10% above a
        # peak S/N of 10, within 30% for the faintest stamp (its wings sink in the noise)
        flux = 10 ** (-0.4 * (mag - 25.95))
        tol = 0.1 if out.peak_snr > 10 else 0.3
        assert out.image.sum() == pytest.approx(flux, rel=tol)


def test_wavelet_denoiser_cuts_the_noise_and_keeps_the_galaxy():
    galaxy, stamp = _blob()
    out = denoise_stamp(stamp, 0.05, smoothing=1.0)
    foot = clean_stamp(stamp, 0.05).weight
    far = foot == 0
    assert np.std(out[far]) < 0.35 * np.std(stamp[far])
    assert out.sum() == pytest.approx(galaxy.sum(), rel=0.05)
    assert np.abs(out - galaxy).max() < 0.3 * galaxy.max()
    ratio = residual_noise_ratio(stamp, 0.05, foot, smoothing=1.0)
    assert 0.1 < ratio < 0.6
    assert residual_noise_ratio(stamp, 0.05, np.zeros_like(foot)) == 1.0
    with pytest.raises(CosmosError, match="noise sigma"):
        denoise_stamp(stamp, -1.0)


def test_dimmed_galaxies_start_at_their_own_brightest_magnitude():
    from subslope.simulation.sources import brightest_magnitude

    src = {"mag_renormalize": [20.5, 23.0], "clean": {"max_noise_fraction": 1.0}}
    assert brightest_magnitude(0.4, src) == 20.5
    assert brightest_magnitude(10.0, src) == pytest.approx(23.0)
    assert np.isnan(brightest_magnitude(0.4, {"mag_renormalize": None}))
