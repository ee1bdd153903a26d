"""The configured set of real lenses: which folder and catalogue the HST stages read, the
manifest of their SHA-256 sums, and the checks every cutout passes before any job.

``observations.folder: null`` (the default) is the shipped set, the 13 lenses of the
reference analysis fetched into ``data.resources_dir/hst`` and checked against the data
registry. Any other folder holds cutouts (``.npy`` or FITS, e⁻/s per pixel), a catalogue
(``observations.catalog``, columns of :data:`subslope.io.observations.CATALOG_COLUMNS`
plus the optional ``exposure_time``, ``pixel_scale`` and ``psf_file``) and
``manifest.sha256``, written once by ``subslope observations add FOLDER``
(:func:`write_manifest`) and checked on every run (:func:`manifest_problems`).

Every cutout is checked against the simulated instrument (:func:`cutout_problems`): it
reads, has the simulated shape, finite values, the simulated pixel scale, and a noise
level that fits e⁻/s (a cutout in counts or ADU has a pixel noise about
exposure-time times larger). A lens whose θ_E lies outside the training prior is a
warning, not a refusal (:func:`subslope.plan.theta_e_warnings`): four of the shipped 13
lie above the reference prior's 1.3″.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "MANIFEST",
    "UNITS_FACTOR",
    "observation_folder",
    "observation_files",
    "write_manifest",
    "manifest_problems",
    "pixel_noise",
    "expected_noise",
    "cutout_problems",
]

#: The manifest of a configured set of cutouts: ``<sha256>  <path in the folder>`` lines.
MANIFEST = "manifest.sha256"

#: A cutout whose pixel noise differs from the e⁻/s noise of its exposure by more than
#: this factor is refused (in counts it is ~exposure time ≈ 10³ times larger).
UNITS_FACTOR = 10.0


def observation_folder(config: Mapping[str, Any]) -> tuple[Path, Path, bool]:
    """``(folder, catalogue, shipped)`` of the configured lenses; ``shipped`` is True for
    the 13 lenses of the reference analysis (``observations.folder: null``)."""
    obs = config["observations"]
    if obs["folder"] is None:
        folder = Path(config["data"]["resources_dir"]) / "hst"
        return folder, folder / "catalog.csv", True
    folder = Path(obs["folder"])
    return folder, folder / obs["catalog"], False


def observation_files(folder, catalog) -> list[Path]:
    """The catalogue and every file it names (cutouts and PSF files), in catalogue order
    (:func:`~subslope.io.observations.load_catalog` refuses a name that leaves the
    folder)."""
    from subslope.io.observations import load_catalog

    folder, catalog = Path(folder), Path(catalog)
    files = [catalog]
    for row in load_catalog(catalog):
        files.append(folder / row["file"])
        if row.get("psf_file"):
            files.append(folder / row["psf_file"])
    return files


def write_manifest(folder, catalog) -> Path:
    """Write ``folder/manifest.sha256`` for the catalogue and the files it names; returns
    its path."""
    from subslope.io.atomic import write_text
    from subslope.io.resources import sha256sum

    folder = Path(folder)
    lines = [
        f"{sha256sum(p)}  {p.relative_to(folder).as_posix()}"
        for p in observation_files(folder, catalog)
    ]
    return write_text(folder / MANIFEST, "\n".join(lines) + "\n")


def manifest_problems(folder, catalog) -> list[str]:
    """What does not match ``folder/manifest.sha256``: a missing manifest, a file missing
    or changed since it was written, a catalogued file it does not list."""
    from subslope.io.observations import ObservationError, inside_folder
    from subslope.io.resources import sha256sum

    folder = Path(folder)
    path = folder / MANIFEST
    fix = f"check the files, then run `subslope observations add {folder}` to record them"
    if not path.is_file():
        return [f"{path} not found: {fix}"]
    listed, out = {}, []
    for k, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip():
            continue
        digest, sep, name = line.strip().partition("  ")
        if not (sep and re.fullmatch(r"[0-9a-f]{64}", digest) and name):
            out.append(f"{path} line {k} is not '<sha256>  <file>' ({line[:80]!r}): {fix}")
        elif not inside_folder(name):
            out.append(
                f"{path} line {k} names {name!r}, outside {folder}: a manifest lists files "
                f"of its folder only; {fix}"
            )
        else:
            listed[name] = digest
    for name, digest in listed.items():
        file = folder / name
        if not file.is_file():
            out.append(f"{file} (in {path}) is missing")
        elif sha256sum(file) != digest:
            out.append(f"{file} changed since {path} was written: {fix}")
    try:
        named = observation_files(folder, catalog)
    except ObservationError as exc:
        return out + [str(exc)]
    for file in named:
        if file.relative_to(folder).as_posix() not in listed:
            out.append(f"{file} is not in {path}: {fix}")
    return out


def pixel_noise(image) -> float:
    """Robust pixel noise (image units): 1.4826 · MAD of neighbour differences / √2 in a
    15-pixel frame at the border, where the sky dominates."""
    im = np.asarray(image, dtype=np.float64)
    frame = np.zeros(im.shape, bool)
    w = max(1, min(15, im.shape[0] // 4, im.shape[1] // 4))
    frame[:w], frame[-w:], frame[:, :w], frame[:, -w:] = True, True, True, True
    d = np.diff(im, axis=1)[frame[:, 1:]]
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0))


def expected_noise(instrument: Mapping[str, Any], exposure_time: float | None = None) -> float:
    """Pixel noise in e⁻/s of an empty sky exposure of the configured instrument
    (``instrument`` section; ``exposure_time`` in s overrides its total): sky and read
    noise, √(sky·t + n_exp·read²)/t."""
    t = float(exposure_time or instrument["exposure_time"])
    pix = float(instrument["pixel_scale"])
    sky = 10.0 ** (-0.4 * (instrument["sky_brightness"] - instrument["zero_point"])) * pix * pix
    n_exp = int(instrument["num_exposures"])
    return math.sqrt(sky * t + n_exp * instrument["read_noise"] ** 2) / t


def cutout_problems(config: Mapping[str, Any], folder, catalog) -> list[str]:
    """Every cutout of the set against the simulated instrument, one line per problem
    naming the file (and the catalogue column where one is at fault)."""
    from subslope.io.observations import ObservationError, load_catalog, load_image

    inst = config["instrument"]
    shape = (int(inst["npix"]), int(inst["npix"]))
    try:
        rows = load_catalog(catalog)
    except ObservationError as exc:
        return [str(exc)]
    out = []
    for row in rows:
        file = Path(folder) / row["file"]
        where = f"{file} ({row['system']}, {catalog})"
        scale = row.get("pixel_scale")
        if scale is not None and not math.isclose(scale, inst["pixel_scale"], rel_tol=1e-6):
            out.append(
                f"{where}: column pixel_scale = {scale} differs from the simulated "
                f"instrument.pixel_scale = {inst['pixel_scale']}; resample the cutout"
            )
        try:
            image = load_image(file, shape)
        except ObservationError as exc:
            out.append(f"{exc} (instrument.npix = {inst['npix']})")
            continue
        ratio = pixel_noise(image) / expected_noise(inst, row.get("exposure_time"))
        if not 1.0 / UNITS_FACTOR <= ratio <= UNITS_FACTOR:
            out.append(
                f"{where}: its pixel noise is {ratio:.3g} times the e-/s noise of the "
                "exposure; the cutout must be in e-/s per pixel (one in counts or ADU "
                "has a noise about exposure-time times larger: divide by the exposure "
                "time, and multiply ADU by the gain)"
            )
        if row.get("psf_file"):
            out += _psf_file_problems(Path(folder) / row["psf_file"], where)
    return out


def _psf_file_problems(path: Path, where: str) -> list[str]:
    from subslope.io.observations import ObservationError, load_image

    try:
        psf = load_image(path, _shape_of(path))
    except ObservationError as exc:
        return [f"{where}: column psf_file: {exc}"]
    if psf.shape[0] % 2 == 0 or psf.shape[1] % 2 == 0 or not psf.sum() > 0:
        return [f"{where}: column psf_file: {path} must be an odd-sized image with a positive sum"]
    return []


def _shape_of(path: Path) -> tuple[int, int]:
    if path.suffix.lower() == ".npy":
        return tuple(np.load(path, mmap_mode="r").shape)  # type: ignore[return-value]
    from astropy.io import fits

    with fits.open(path) as hdus:
        for hdu in hdus:
            if hdu.data is not None and hdu.data.ndim == 2:
                return tuple(hdu.data.shape)  # type: ignore[return-value]
    return (0, 0)
