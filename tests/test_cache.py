"""The cache of finished results (subslope.io.shard_cache, subslope.campaigns.cache): entries of
files with their manifest, the lens-light fits' key, and `subslope cache du` / `prune`
on a cache built from the tiny campaign's own shards."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
import yaml

from subslope import config as cfgmod
from subslope.campaigns.cache import cache_usage, campaigns_in_use, prune_cache
from subslope.cli import main
from subslope.io.shard_cache import (
    MANIFEST,
    cached_entry,
    cached_path,
    identity_path,
    put_files_in_cache,
    put_in_cache,
    shard_identity,
    take_files_from_cache,
    take_from_cache,
)
from subslope.plan import shard_job_config
from subslope.stages.domain import LENS_LIGHT_FILES, lens_light_fit_key
from subslope.stages.simulate import shard_cache_key

REPO = Path(__file__).resolve().parents[1]


def test_files_round_trip_and_a_changed_file_is_not_taken(tmp_path):
    a, b = tmp_path / "a.csv", tmp_path / "b.yaml"
    a.write_text("x,y\n1,2\n")
    b.write_text("k: 1\n")
    entry = put_files_in_cache(tmp_path / "cache", "fits", "k1", {"a.csv": a, "b.yaml": b})
    assert entry == cached_entry(tmp_path / "cache", "fits", "k1")
    assert (entry / MANIFEST).is_file()
    out = {"a.csv": tmp_path / "out" / "a.csv", "b.yaml": tmp_path / "out" / "b.yaml"}
    assert take_files_from_cache(tmp_path / "cache", "fits", "k1", out)
    assert out["a.csv"].read_text() == "x,y\n1,2\n" and out["b.yaml"].read_text() == "k: 1\n"
    assert not take_files_from_cache(tmp_path / "cache", "fits", "k2", out)  # no such key
    (entry / "b.yaml").unlink()  # another name: the entry's own file changes
    (entry / "b.yaml").write_text("k: 2\n")
    assert not take_files_from_cache(tmp_path / "cache", "fits", "k1", out)
    assert not entry.exists()  # removed, to be computed again
    put_files_in_cache(tmp_path / "cache", "fits", "k3", {"a.csv": a, "b.yaml": b})
    (cached_entry(tmp_path / "cache", "fits", "k3") / MANIFEST).unlink()  # interrupted entry
    assert not take_files_from_cache(tmp_path / "cache", "fits", "k3", out)


def test_the_lens_light_key_follows_its_inputs_only(tmp_path, data_dir):
    hst = tmp_path / "hst"
    shutil.copytree(data_dir / "hst", hst)
    config = cfgmod.load(REPO / "config" / "tiny.yaml", env=False)
    config["data"]["resources_dir"] = str(data_dir)
    key = lens_light_fit_key(config, hst)
    other = {**config, "training": {**config["training"], "lr": 0.5}, "run_name": "x"}
    assert lens_light_fit_key(other, hst) == key  # the estimator does not reach the fits
    changes = [
        ("instrument", {**config["instrument"], "pixel_scale": 0.05}),
        ("hst", {**config["hst"], "lens_centre": {**config["hst"]["lens_centre"], "smoothing": 2}}),
    ]
    for section, value in changes:
        assert lens_light_fit_key({**config, section: value}, hst) != key, section
    with open(hst / "catalog.csv", "a") as fh:
        fh.write("\n")
    assert lens_light_fit_key(config, hst) != key  # a file's bytes


@pytest.fixture
def cache_campaign(tiny_run, tmp_path):
    """A config on the tiny campaign with a cache of its own in tmp_path, holding one
    shard each way: referenced (the tiny shard under its own key, linked from a
    results folder), unreferenced and linked, unreferenced alone; and the tiny run's
    lens-light fits under their key."""
    root = tiny_run.parent
    cache = tmp_path / "cache"
    path = tmp_path / "campaign.yaml"
    path.write_text(
        yaml.safe_dump(
            {
                "base": str(root / "config" / "tiny.yaml"),
                "data": {"resources_dir": str(root / "resources")},
                "simulation": {"shard_cache": str(cache)},
                "systematics": {"variants": [], "shard_cache": str(cache)},
            }
        )
    )
    config = cfgmod.load(path, env=False)
    shard = tiny_run / "simulate_shard" / "validation" / "shard_0.h5"
    key = shard_cache_key(shard_job_config(config, "validation"), "validation", 0)
    results = tmp_path / "results"
    results.mkdir()
    shutil.copyfile(shard, results / "kept.h5")
    cached_path(cache, "validation", key).parent.mkdir(parents=True)
    os.link(results / "kept.h5", cached_path(cache, "validation", key))
    os.link(results / "kept.h5", cached_path(cache, "validation", "0" * 64))
    shutil.copyfile(shard, cached_path(cache, "validation", "1" * 64))
    for name in (key, "0" * 64, "1" * 64):  # their identity records make them entries
        ident = shard_identity(cached_path(cache, "validation", name))
        identity_path(cache, "validation", name).write_text(json.dumps(ident))
    # a stray file in the cache folder is not an entry, and prune never removes it
    shutil.copyfile(shard, cached_path(cache, "validation", "stray"))
    fits = tiny_run / "fit_lens_light"
    put_files_in_cache(
        cache,
        "lens_light",
        lens_light_fit_key(config, root / "resources" / "hst"),
        {name: fits / name for name in LENS_LIGHT_FILES.values()},
    )
    return {"path": path, "cache": cache, "key": key}


def test_du_tells_what_uses_each_entry(cache_campaign, capsys):
    usage = cache_usage(campaigns_in_use([cache_campaign["path"]]))
    entries = {e.key: e for e in usage[cache_campaign["cache"]]}
    assert len(entries) == 4
    assert entries[cache_campaign["key"]].used_by == ["tiny"]
    assert entries[cache_campaign["key"]].held and entries["0" * 64].held
    assert not entries["0" * 64].used_by and not entries["1" * 64].used_by
    assert not entries["1" * 64].held
    (fit,) = [e for e in entries.values() if e.kind == "lens_light"]
    assert fit.used_by == ["tiny"] and not fit.held  # entered as a copy of its own
    assert main(["cache", "du", "--config", str(cache_campaign["path"]), "--entries"]) == 0
    out = capsys.readouterr().out
    assert f"{cache_campaign['cache']}: 4 entries" in out
    assert "validation" in out and "lens_light" in out and "used by: tiny" in out


def test_prune_keeps_what_is_used_or_linked(cache_campaign, capsys):
    cache, key = cache_campaign["cache"], cache_campaign["key"]
    argv = ["cache", "prune", "--config", str(cache_campaign["path"])]
    assert main([*argv, "--dry-run"]) == 0
    assert "would remove 1 entries" in capsys.readouterr().out
    assert cached_path(cache, "validation", "1" * 64).exists()
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "removed 1 entries" in out and "kept 1 unreferenced entries" in out
    assert not cached_path(cache, "validation", "1" * 64).exists()
    assert cached_path(cache, "validation", "0" * 64).exists()  # a results/ file links it
    assert cached_path(cache, "validation", key).exists()
    assert main([*argv, "--force"]) == 0
    assert "removed 1 entries" in capsys.readouterr().out
    assert not cached_path(cache, "validation", "0" * 64).exists()
    assert (cache_campaign["path"].parent / "results" / "kept.h5").exists()
    left = cache_usage(campaigns_in_use([cache_campaign["path"]]))[cache]
    assert sorted(e.kind for e in left) == ["lens_light", "shard"]
    assert all(e.used_by for e in left)
    assert cached_path(cache, "validation", "stray").exists()


def test_prune_of_a_config_without_a_cache(tmp_path, capsys):
    path = tmp_path / "c.yaml"
    path.write_text(
        yaml.safe_dump(
            {
                "base": str(REPO / "config" / "tiny.yaml"),
                "simulation": {"shard_cache": None},
                "systematics": {"variants": []},
            }
        )
    )
    assert prune_cache(cache_usage(campaigns_in_use([path]))) == ([], [])
    assert main(["cache", "du", "--config", str(path)]) == 0
    assert "no campaign keeps a cache" in capsys.readouterr().out


def test_a_cached_shard_is_a_file_of_its_own_and_must_be_the_shard_of_its_key(tiny_run, tmp_path):
    """Overwriting a results/ shard (a restore "from a copy") cannot reach the cache, and a
    cache file that is not the shard its key names is refused and removed."""
    cache = tmp_path / "cache"
    shard0 = tiny_run / "simulate_shard" / "train" / "shard_0.h5"
    shard1 = tiny_run / "simulate_shard" / "train" / "shard_1.h5"
    result = tmp_path / "results" / "shard_0.h5"
    result.parent.mkdir()
    shutil.copyfile(shard0, result)
    put_in_cache(cache, "train", "k0", result)
    assert os.stat(result).st_ino != os.stat(cached_path(cache, "train", "k0")).st_ino
    with open(shard1, "rb") as src, open(result, "r+b") as dst:  # cp writes into the inode
        dst.truncate(0)
        shutil.copyfileobj(src, dst)
    out = tmp_path / "taken.h5"
    assert take_from_cache(cache, "train", "k0", out, shard=0)
    assert shard_identity(out)["shard_index"] == 0
    # the cache file itself replaced by another shard's bytes: not the shard of its key
    shutil.copyfile(shard1, cached_path(cache, "train", "k0"))
    assert not take_from_cache(cache, "train", "k0", tmp_path / "bad.h5", shard=0)
    assert not cached_path(cache, "train", "k0").exists()
    assert not identity_path(cache, "train", "k0").exists()
    # asked for the wrong index (a key that names shard 1): refused as well
    put_in_cache(cache, "train", "k1", shard0)
    assert not take_from_cache(cache, "train", "k1", tmp_path / "bad.h5", shard=1)


@pytest.mark.parametrize("folder", ["results", "results/cache", "."])
def test_a_cache_folder_overlapping_results_is_refused(tmp_path, folder, monkeypatch, capsys):
    from subslope.plan import cache_folder_problems

    config = {"simulation": {"shard_cache": folder}, "systematics": {"shard_cache": None}}
    (problem,) = cache_folder_problems(config, tmp_path)
    assert "simulation.shard_cache" in problem and "overlaps results/" in problem
    assert cache_folder_problems({"simulation": {"shard_cache": ".cache/x"}}, tmp_path) == []
    (tmp_path / "results" / "analyze_hst").mkdir(parents=True)
    kept = tmp_path / "results" / "analyze_hst" / "profiles.h5"
    kept.write_bytes(b"a finished result")
    path = tmp_path / "c.yaml"
    path.write_text(
        yaml.safe_dump(
            {
                "base": str(Path(__file__).parents[1] / "config" / "tiny.yaml"),
                "simulation": {"shard_cache": folder},
                "systematics": {"variants": []},
            }
        )
    )
    monkeypatch.chdir(tmp_path)
    assert main(["cache", "prune", "--config", str(path)]) == 1
    assert "overlaps results/" in capsys.readouterr().err
    assert kept.exists()
