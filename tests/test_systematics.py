"""The systematics variants (subslope.campaigns.systematics) and the shard cache
(subslope.io.shard_cache): variant configs, the changes column, cache keys, and two
variants of the tiny campaign run through `subslope systematics` sharing its shards."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import h5py
import pandas as pd
import pytest
import yaml
from conftest import REPO_ROOT, shared_data_dir

from subslope import config as C
from subslope.campaigns.systematics import (
    SYSTEMATICS_COLUMNS,
    SystematicsError,
    config_changes,
    read_variants,
    reference_config,
    variant_config,
)
from subslope.io.shard_cache import CODE_PARTS, take_from_cache
from subslope.plan import plan_problems, shard_job_config
from subslope.stages.simulate import shard_cache_key

CONFIG = REPO_ROOT / "config" / "config.yaml"
TINY = REPO_ROOT / "config" / "tiny.yaml"
SHIPPED = ("realism", "paper", "lens_light_table1", "sheet_origin", "sources_bundled",
           "sources_multi_sersic")  # fmt: skip


def _campaign(path: Path = CONFIG) -> dict:
    return C.read_files([path])


@pytest.mark.parametrize("path", [CONFIG, TINY], ids=["reduced", "tiny"])
def test_every_shipped_variant_is_a_valid_campaign(path):
    variants = read_variants(_campaign(path), root=REPO_ROOT)
    assert tuple(v.name for v in variants) == SHIPPED
    for v in variants:
        cfg = C.validate(v.config)
        assert cfg["run_name"] == v.name
        assert v.folder == REPO_ROOT / "results" / "variants" / v.name
        assert plan_problems(cfg) == [], v.name


def test_variant_config_layers_and_absolute_paths(tmp_path):
    campaign = _campaign()
    overlay = {"run_name": "x", "seed": 7}
    merged = variant_config(campaign, overlay, root=tmp_path, shard_cache="cache")
    assert merged["seed"] == 7
    assert "systematics" not in merged
    assert merged["data"]["mirror"] == str((tmp_path / "../shared/data").resolve())
    assert merged["data"]["resources_dir"] == str(tmp_path / "resources")
    assert merged["simulation"]["shard_cache"] == str(tmp_path / "cache")
    # systematics.common sits between the campaign and the overlay
    assert merged["simulation"]["scenes"]["train"]["n_shards"] == 3
    assert merged["simulation"]["multipliers"] == [1.0]


def test_the_changes_column_lists_what_each_variant_changes():
    campaign = _campaign()
    reference = reference_config(campaign)
    changes = {v.name: config_changes(reference, v.config) for v in read_variants(campaign)}
    assert changes["realism"] == "none"
    assert changes["lens_light_table1"] == "scenes.*.lens_light.prior=table1"
    assert changes["sources_bundled"] == "simulation.sources.folder=[cosmos]"
    assert changes["sources_multi_sersic"] == "scenes.*.source.kind=multi_sersic"
    sheet = changes["sheet_origin"].split("; ")
    assert "scenes.{nfw,test_epl,tnfw,train,validation}.subhalos.sheet_centre=origin" in sheet
    # every scene the variant simulates (null_nosub is switched off by systematics.common)
    assert "scenes.*.los.sheet_centre=origin" in sheet
    paper = set(changes["paper"].split("; "))
    assert paper == set(sheet) | {
        "scenes.*.lens_light.prior=table1",
        "scenes.*.components.sky=false",
        "simulation.sources.folder=[cosmos]",
        # the paper's theta_E prior and the reference code's CDM sets
        "scenes.*.main_lens.theta_e.high=1.3",
        "scenes.{nfw,tnfw}.subhalos.count.high=12000",
        "scenes.{nfw,tnfw}.subhalos.placement=landing",
        "scenes.{nfw,tnfw}.subhalos.threshold_fraction=0.01",
    }


def _write(path: Path, data: dict) -> Path:
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


@pytest.mark.parametrize(
    "overlay, message",
    [
        ({"seed": 3}, "must set a run_name of its own"),
        ({"run_name": "reduced"}, "must set a run_name of its own"),
        ({"run_name": "v", "seed": -1}, "config key seed"),
        ({"run_name": "v", "simulation": {"sources": {"folder": []}}}, "simulation.sources"),
        (
            {"run_name": "v", "instrument": {"noise_correlation": [0.5, 0.3]}},
            r"instrument.noise_correlation = \[0.5, 0.3\]: a range",
        ),
    ],
    ids=["no-run-name", "campaign-run-name", "bad-seed", "bad-folder", "plan-problem"],
)
def test_a_bad_variant_file_is_named(tmp_path, overlay, message):
    variant = _write(tmp_path / "v.yaml", overlay)
    campaign = C.deep_merge(_campaign(), {"systematics": {"variants": [str(variant)]}})
    with pytest.raises(SystematicsError, match=message) as info:
        read_variants(campaign, root=REPO_ROOT)
    assert str(variant) in str(info.value)


def test_two_variants_of_one_name_and_a_missing_file_are_refused(tmp_path):
    a = _write(tmp_path / "a.yaml", {"run_name": "same"})
    b = _write(tmp_path / "b.yaml", {"run_name": "same"})
    campaign = C.deep_merge(_campaign(), {"systematics": {"variants": [str(a), str(b)]}})
    with pytest.raises(SystematicsError, match="both have run_name 'same'"):
        read_variants(campaign)
    campaign["systematics"]["variants"] = [str(tmp_path / "gone.yaml")]
    with pytest.raises(SystematicsError, match="gone.yaml does not exist"):
        read_variants(campaign)


def test_the_cache_key_follows_the_images_and_not_the_shard_count():
    config = C.load(TINY, env=False)
    key = shard_cache_key(shard_job_config(config, "test_epl"), "test_epl", 0)
    more = C.deep_merge(config, {"simulation": {"scenes": {"test_epl": {"n_shards": 5}}}})
    assert shard_cache_key(shard_job_config(more, "test_epl"), "test_epl", 0) == key
    assert shard_cache_key(shard_job_config(config, "test_epl"), "test_epl", 1) != key
    for change in (
        {"seed": 99},
        {"scenes": {"test_epl": {"subhalos": {"sheet_centre": "origin"}}}},
        {"scenes": {"test_epl": {"lens_light": {"prior": "table1"}}}},
        {"simulation": {"render": {"dtype": "float64"}}},
        {"simulation": {"render": {"batch_images": 7}}},
        {"simulation": {"scenes": {"test_epl": {"images_per_shard": 10}}}},
    ):
        other = C.deep_merge(config, change)
        assert shard_cache_key(shard_job_config(other, "test_epl"), "test_epl", 0) != key, change
    for run_only in ({"device": "cpu"}, {"compile_cache": "elsewhere"}):
        other = C.deep_merge(config, {"simulation": {"render": run_only}})
        assert shard_job_config(other, "test_epl") == shard_job_config(config, "test_epl")
        assert shard_cache_key(shard_job_config(other, "test_epl"), "test_epl", 0) == key


def test_the_code_parts_of_the_key_exist():
    package = REPO_ROOT / "src" / "subslope"
    assert all((package / part).exists() for part in CODE_PARTS)
    assert "nre" not in CODE_PARTS and "stages" not in CODE_PARTS


def _shards(results: Path) -> list[Path]:
    return sorted((results / "simulate_shard").rglob("*.h5"))


def test_a_corrupt_cached_shard_is_removed_not_used(tiny_run, tmp_path):
    from subslope.io.shard_cache import put_in_cache, shard_identity

    shard = _shards(tiny_run)[0]
    scene = shard_identity(shard)["scene"]
    cached = put_in_cache(tmp_path / "cache", scene, "k", shard)  # a copy of its own
    assert take_from_cache(tmp_path / "cache", scene, "k", tmp_path / "good.h5")
    assert (tmp_path / "good.h5").read_bytes() == shard.read_bytes()
    with h5py.File(cached, "r") as fh:
        offset = fh["images"].id.get_chunk_info(0).byte_offset
    with open(cached, "r+b") as fh:
        fh.seek(offset + 10)
        fh.write(b"\xff\xff\xff\xff")
    assert not take_from_cache(tmp_path / "cache", scene, "k", tmp_path / "out.h5")
    assert not cached.exists() and not (tmp_path / "out.h5").exists()


@pytest.fixture(scope="module")
def systematics_run(tiny_run, tmp_path_factory):
    """`subslope systematics` over the realism and sheet_origin variants of the tiny
    campaign, in the tiny run's folder (its data and its shard cache), writing the
    variants and the table into a folder of their own."""
    root = tiny_run.parent
    out = tmp_path_factory.mktemp("systematics")
    overlay = _write(
        out / "where.yaml",
        {"systematics": {"folder": str(out / "variants"), "table": str(out / "table")}},
    )
    exe = Path(sys.executable).with_name("subslope")
    command = [str(exe), "systematics", "--config", "config/tiny.yaml", str(overlay),
               "--only", "realism", "sheet_origin", "--cores", "2"]  # fmt: skip
    env = dict(os.environ, OMP_NUM_THREADS="1", SUBSLOPE_DATA_MIRROR=str(shared_data_dir()))
    proc = subprocess.run(command, cwd=root, env=env, capture_output=True, text=True, timeout=1500)
    assert proc.returncode == 0, proc.stdout[-5000:] + proc.stderr[-5000:]
    return {"root": root, "out": out, "command": command, "env": env}


def test_the_table_has_one_row_per_variant_from_its_summary(systematics_run):
    out = systematics_run["out"]
    table = pd.read_csv(out / "table" / "systematics.csv", keep_default_na=False)
    assert list(table.columns) == list(SYSTEMATICS_COLUMNS)
    assert list(table["variant"]) == ["realism", "sheet_origin"]
    assert (out / "table" / "systematics.md").read_text().count("\n| ") == 2
    for ext in ("pdf", "png"):
        assert (out / "table" / "figures" / f"systematics.{ext}").stat().st_size > 1000
    for row in table.to_dict("records"):
        results = out / "variants" / row["variant"] / "results"
        hst = pd.read_csv(results / "hst_result.csv").iloc[0]
        assert row["hst_gamma_mle"] == pytest.approx(float(hst["gamma_mle"]))
        assert row["hst_lower"] == pytest.approx(float(hst["lower"]))
        coverage = pd.read_csv(results / "coverage.csv").set_index("n_images")
        assert row["n_max"] == 2
        assert row["coverage_nmax"] == pytest.approx(float(coverage.loc[2, "coverage"]))
        assert row["domain_lenses"] == 13
        assert row["null_scene"] == "null_nosub_los"
    assert table.set_index("variant").loc["realism", "changes"] == "none"


def _files(results: Path) -> dict[Path, Path]:
    return {p.relative_to(results): p for p in _shards(results)}


def test_variants_share_the_shards_they_do_not_alter(systematics_run, tiny_run):
    variants = systematics_run["out"] / "variants"
    own = _files(tiny_run)
    realism = _files(variants / "realism" / "results")
    # systematics.common switches the reference grid and the matched controls off
    extra = {str(p).split("/")[1] for p in own.keys() - realism.keys()}
    assert realism.keys() <= own.keys() and extra == {
        "nfw_ref",
        "tnfw_ref",
        "epl_control_15",
        "epl_control_24",
        "epl_control_ref_15",
        "epl_control_ref_24",
    }
    for rel, path in realism.items():  # every shard of realism is the tiny campaign's
        assert path.read_bytes() == own[rel].read_bytes(), rel
        # as a file of its own: Snakemake touches the variant's outputs
        assert not os.path.samefile(path, own[rel]), rel
    logs = variants / "realism" / "logs" / "simulate_shard"
    assert all("taken from the cache" in p.read_text() for p in logs.rglob("*.log"))
    sheet = _files(variants / "sheet_origin" / "results")
    same = {str(p) for p in sheet if sheet[p].read_bytes() == own[p].read_bytes()}
    assert same == {"simulate_shard/null_nosub/shard_0.h5"}  # no subhalos, no LoS
    logs = variants / "sheet_origin" / "logs" / "simulate_shard"
    assert "taken from the cache" in (logs / "null_nosub" / "shard_0.log").read_text()
    assert "taken from the cache" not in (logs / "train" / "shard_0.log").read_text()
    # the same fits of the HST lens light, taken from the cache
    fits = "fit_lens_light/lens_light_fits.csv"
    for variant in ("realism", "sheet_origin"):
        assert (variants / variant / "results" / fits).read_text() == (tiny_run / fits).read_text()
        log = (variants / variant / "logs" / "fit_lens_light.log").read_text()
        assert "taken from the cache" in log, variant


def test_the_campaign_has_nothing_to_do_after_its_variants(systematics_run, tiny_run, data_dir):
    """The variants' runs leave the campaign's files as they were: its next run, judging
    by modification times alone (as Snakemake does for files above its 1 MB checksum
    limit, i.e. every shard of a real campaign), does nothing."""
    proc = subprocess.run(
        [str(Path(sys.executable).with_name("snakemake")), "-n", "--configfile",
         "config/tiny.yaml", "--max-checksum-file-size", "1"],
        cwd=tiny_run.parent, env=systematics_run["env"], capture_output=True, text=True,
        timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Nothing to be done" in proc.stdout + proc.stderr, proc.stdout[-3000:]


def test_a_second_call_reruns_nothing(systematics_run):
    proc = subprocess.run(
        systematics_run["command"], cwd=systematics_run["root"], env=systematics_run["env"],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stderr.count("Nothing to be done") == 2, proc.stderr[-3000:]


CHILD = """
import pathlib, signal, sys, time
done = pathlib.Path(sys.argv[1])
def stop(*_):
    done.write_text("stopped its jobs and released its lock")
    sys.exit(1)
signal.signal(signal.SIGINT, stop)
done.with_name("ready").write_text("")
time.sleep(60)
"""

PARENT = """
import sys
from subslope.campaigns.systematics import run_to_end
try:
    run_to_end([sys.executable, "-c", sys.argv[1], sys.argv[2]])
except KeyboardInterrupt:
    sys.exit(130)
"""


def test_an_interrupted_campaign_command_lets_snakemake_stop(tmp_path):
    """Ctrl-C of `subslope seeds` or `systematics` interrupts the Snakemake it runs and
    waits for it (subprocess.run would kill it, leaving its lock behind)."""
    import signal
    import time

    done = tmp_path / "done"
    parent = subprocess.Popen([sys.executable, "-c", PARENT, CHILD, str(done)])
    deadline = time.time() + 60
    while not (tmp_path / "ready").exists() and time.time() < deadline:
        time.sleep(0.1)
    parent.send_signal(signal.SIGINT)  # to the command only: it must pass it on
    assert parent.wait(timeout=60) == 130
    assert done.read_text() == "stopped its jobs and released its lock"


def test_the_workflow_profile_resumes_an_interrupted_run():
    profile = yaml.safe_load((REPO_ROOT / "profiles" / "default" / "config.yaml").read_text())
    assert profile == {"rerun-incomplete": True}
