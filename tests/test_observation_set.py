"""A set of real lenses of one's own: five of the shipped cutouts renamed (one rotated by
90°) as a configured observation set, its manifest, the checks every cutout passes, and
the HST stages of the tiny campaign run on it."""

from __future__ import annotations

import csv
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from conftest import REPO_ROOT, run_snakemake

from subslope import config as C
from subslope.cli import main
from subslope.io.observation_set import (
    MANIFEST,
    cutout_problems,
    expected_noise,
    manifest_problems,
    pixel_noise,
)
from subslope.io.observations import load_hst
from subslope.plan import plan_problems, theta_e_warnings

TINY = REPO_ROOT / "config" / "tiny.yaml"
COLUMNS = ["file", "system", "z_lens", "z_source", "theta_E_arcsec", "exposure_time"]


def _make_set(data_dir: Path, folder: Path, *, counts: bool = False) -> list[dict]:
    """Five shipped cutouts as LENS1..LENS5 (LENS2 rotated by 90°); with ``counts`` a sixth
    one multiplied by its exposure time (counts, not e-/s)."""
    folder.mkdir(parents=True, exist_ok=True)
    shipped = list(csv.DictReader(open(data_dir / "hst" / "catalog.csv", encoding="utf-8")))
    rows = []
    for k, r in enumerate(shipped[: 6 if counts else 5]):
        image = np.load(data_dir / "hst" / r["file"]).astype("<f4")
        image = np.rot90(image) if k == 1 else image * 2200.0 if k == 5 else image
        name = f"LENS{k + 1}"
        np.save(folder / f"{name}.npy", image)
        rows.append(dict(zip(COLUMNS, [f"{name}.npy", name, r["z_lens"], r["z_source"],
                                       r["theta_E_arcsec"], "2200"])))  # fmt: skip
    with open(folder / "catalog.csv", "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    return rows


def _config(folder: Path | None = None, **more) -> dict:
    raw = C.read_files([TINY])
    if folder is not None:
        raw["observations"] = {"folder": str(folder)}
        raw["hst"].update({"combine": ["LENS1", "LENS2"], "show": ["LENS1"], "highlight": []})
    return C.validate(C.deep_merge(raw, more))


def test_the_shipped_cutouts_have_the_noise_of_e_per_s(data_dir):
    inst = _config()["instrument"]
    ratios = [pixel_noise(o.image) / expected_noise(inst) for o in load_hst(data_dir / "hst")]
    assert 1.0 < min(ratios) and max(ratios) < 2.0  # drizzled F814W, e-/s: 1.2-1.6


def test_a_cutout_in_counts_is_refused_naming_the_file(data_dir, tmp_path, capsys):
    _make_set(data_dir, tmp_path, counts=True)
    problems = cutout_problems(_config(), tmp_path, tmp_path / "catalog.csv")
    assert len(problems) == 1 and "LENS6.npy (LENS6" in problems[0]
    assert re.search(r"pixel noise is [\d.e+]+ times .* in e-/s per pixel", problems[0])
    assert main(["observations", "add", str(tmp_path), "--config", str(TINY)]) == 1
    assert "LENS6.npy" in capsys.readouterr().err and not (tmp_path / MANIFEST).exists()


def _crop(f):
    np.save(f / "LENS3.npy", np.zeros((90, 100)))


def _nan(f):
    np.save(f / "LENS3.npy", np.full((100, 100), np.nan))


@pytest.mark.parametrize(
    "edit, message",
    [
        (_crop, r"LENS3.npy: image has shape \(90, 100\)"),
        (_nan, r"LENS3.npy: 10000 non-finite"),
        (lambda f: _column(f, "pixel_scale", "0.05"), r"column pixel_scale = 0.05 differs"),
        (lambda f: _column(f, "psf_file", "LENS1.npy"), r"column psf_file: .* odd-sized"),
    ],
)
def test_every_bad_cutout_is_named(data_dir, tmp_path, edit, message):
    _make_set(data_dir, tmp_path)
    edit(tmp_path)
    problems = cutout_problems(_config(), tmp_path, tmp_path / "catalog.csv")
    assert any(re.search(message, p) for p in problems), problems


def _column(folder: Path, name: str, value: str) -> None:
    table = pd.read_csv(folder / "catalog.csv")
    table[name] = value
    table.to_csv(folder / "catalog.csv", index=False)


def test_the_manifest_is_written_once_and_checked(data_dir, tmp_path):
    _make_set(data_dir, tmp_path)
    catalog = tmp_path / "catalog.csv"
    assert "manifest.sha256 not found" in manifest_problems(tmp_path, catalog)[0]
    assert main(["observations", "add", str(tmp_path), "--config", str(TINY)]) == 0
    listed = (tmp_path / MANIFEST).read_text().split()
    assert listed[1::2] == ["catalog.csv"] + [f"LENS{k}.npy" for k in range(1, 6)]
    assert manifest_problems(tmp_path, catalog) == []
    config = _config(tmp_path)
    assert plan_problems(config) == []
    np.save(tmp_path / "LENS4.npy", np.load(tmp_path / "LENS4.npy") * 1.001)
    assert "LENS4.npy changed since" in " ".join(plan_problems(config))
    (tmp_path / "LENS4.npy").unlink()
    assert "LENS4.npy (in" in " ".join(manifest_problems(tmp_path, catalog))
    # θ_E outside the training prior is said, not refused: every lens lies inside the
    # shipped prior, 4 of the 13 lie above the reference paper's 1.3"
    assert theta_e_warnings(config, catalog) == []
    paper = {"dist": "uniform", "low": 0.9, "high": 1.3}
    narrow = _config(tmp_path, scenes={"train": {"main_lens": {"theta_e": paper}}})
    assert [w.split(" ")[0] for w in theta_e_warnings(narrow, catalog)] == [
        "LENS1",
        "LENS3",
        "LENS5",
    ]


def test_a_set_too_small_for_the_joint_prior_is_refused_before_any_job(data_dir, tmp_path):
    rows = _make_set(data_dir, tmp_path)[:3]
    with open(tmp_path / "catalog.csv", "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    for extra in ("LENS4.npy", "LENS5.npy"):
        (tmp_path / extra).unlink()
    assert main(["observations", "add", str(tmp_path), "--config", str(TINY)]) == 0
    problems = " ".join(plan_problems(_config(tmp_path)))
    assert "config key observations.folder" in problems and "lists 3 lens(es)" in problems
    assert "needs at least 5" in problems and "stages.domain: false" in problems
    assert plan_problems(_config(tmp_path, stages={"domain": False})) == []


def test_manifest_lines_are_read_strictly_and_stay_in_the_folder(data_dir, tmp_path):
    from subslope.io.resources import sha256sum

    folder = tmp_path / "set"
    _make_set(data_dir, folder)
    assert main(["observations", "add", str(folder), "--config", str(TINY)]) == 0
    manifest, catalog = folder / MANIFEST, folder / "catalog.csv"
    good = manifest.read_text()
    manifest.write_text(good + "not a manifest line\n")
    problems = manifest_problems(folder, catalog)
    assert len(problems) == 1 and "line 7 is not '<sha256>  <file>'" in problems[0]
    outside = tmp_path / "outside.txt"
    outside.write_text("not a lens\n")
    for name in ("../outside.txt", str(outside)):  # a correct hash does not let it in
        manifest.write_text(good + f"{sha256sum(outside)}  {name}\n")
        problems = manifest_problems(folder, catalog)
        assert len(problems) == 1 and f"names {name!r}, outside" in problems[0], problems
    manifest.write_text(good)
    rows = list(csv.DictReader(open(catalog, encoding="utf-8")))
    rows[0]["file"] = "../outside.txt"
    with open(catalog, "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    assert "file '../outside.txt' must be a path inside the catalogue's folder" in " ".join(
        manifest_problems(folder, catalog)
    )


def test_a_missing_folder_is_refused_by_its_key(tmp_path):
    problems = plan_problems(_config(tmp_path / "nowhere"))
    assert problems == [
        f"config key observations.folder = '{tmp_path / 'nowhere'}': no such folder"
    ]


@pytest.fixture
def campaign_copy(tiny_run, tmp_path):
    dst = tmp_path / "campaign"
    shutil.copytree(tiny_run.parent, dst, symlinks=True, ignore=shutil.ignore_patterns(".*.tmp"))
    return dst


@pytest.mark.slow
def test_the_hst_stages_run_on_a_set_of_ones_own(campaign_copy, data_dir, tmp_path):
    root, lenses = campaign_copy, tmp_path / "lenses"
    _make_set(data_dir, lenses)
    assert main(["observations", "add", str(lenses), "--config", str(TINY)]) == 0
    overlay = root / "config" / "mine.yaml"
    overlay.write_text(yaml.safe_dump({
        "base": "tiny.yaml", "observations": {"folder": str(lenses)},
        "hst": {"combine": ["LENS1", "LENS2"], "show": ["LENS1"], "highlight": ["LENS2"]},
    }))  # fmt: skip
    proc = run_snakemake(root, "--cores", "2", "--configfile", str(overlay), mirror=data_dir)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    ran = set(re.findall(r"^(?:local)?rule (\w+):", proc.stdout + proc.stderr, re.MULTILINE))
    assert ran == {"plot_hst_gallery", "fit_lens_light", "check_domain", "analyze_hst",
                   "write_summary", "all"}, ran  # fmt: skip
    intervals = pd.read_csv(root / "results" / "analyze_hst" / "intervals.csv")
    assert intervals["system"].tolist() == [f"LENS{k}" for k in range(1, 6)] + ["combined"]
    domain = pd.read_csv(root / "results" / "check_domain" / "domain_check.csv")
    assert domain["system"].tolist() == [f"LENS{k}" for k in range(1, 6)]
    assert "LENS1" in (root / "results" / "summary.md").read_text()
