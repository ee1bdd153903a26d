"""Training seeds (`subslope seeds`): each seed a campaign of its own on the campaign's
shards, and the table of what every training reads."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from conftest import REPO_ROOT, shared_data_dir

from subslope import config as C
from subslope.campaigns.seeds import (
    ESTIMATOR_ONLY,
    SEEDS_COLUMNS,
    SEEDS_CSV,
    seed_variants,
    seeds_markdown,
    summary_command,
)
from subslope.campaigns.systematics import SystematicsError
from subslope.plan import plan_problems
from subslope.stages.summary_hst import meaning_lines, reach_lines, seeds_lines

CONFIG = REPO_ROOT / "config" / "config.yaml"


def test_a_seed_is_the_campaign_with_another_training_seed(tmp_path):
    campaign = C.read_files([CONFIG])
    variants = seed_variants(campaign, [1, 2, 1], root=tmp_path, folder=tmp_path / "s", file=CONFIG)
    assert [v.name for v in variants] == ["reduced_seed1", "reduced_seed2"]
    for seed, v in zip((1, 2), variants):
        cfg = C.validate(v.config)
        assert cfg["training"]["seed"] == seed and cfg["run_name"] == v.name
        assert v.folder == tmp_path / "s" / v.name
        # the campaign's shard cache and data, everything that makes shards unchanged
        assert cfg["simulation"]["shard_cache"] == str(tmp_path / ".cache" / "shard_cache")
        assert cfg["data"]["resources_dir"] == str(tmp_path / "resources")
        reference = C.validate(campaign)
        assert cfg["scenes"] == reference["scenes"] and cfg["seed"] == reference["seed"]
        assert cfg["simulation"]["scenes"] == reference["simulation"]["scenes"]  # no common
        for stage, on in ESTIMATOR_ONLY["stages"].items():
            assert cfg["stages"][stage] is on
        assert cfg["stages"]["train"] and cfg["stages"]["hst"] and cfg["stages"]["calibrate"]
        assert plan_problems(cfg) == []


@pytest.mark.parametrize(
    "change, seeds, message",
    [
        ({"simulation": {"shard_cache": None}}, [1], "shard_cache is null"),
        ({}, [-1], "outside 0 .. 2\\^32-1"),
        ({"training": {"max_epochs": 0}}, [1], "training.max_epochs"),
    ],
)
def test_a_seed_that_cannot_run_is_refused_before_any(tmp_path, change, seeds, message):
    campaign = C.deep_merge(C.read_files([CONFIG]), change)
    with pytest.raises((SystematicsError, C.ConfigError), match=message):
        seed_variants(campaign, seeds, root=tmp_path, folder=tmp_path, file=CONFIG)


ROWS = [
    {"training": "a", "seed": "derived", "hst_gamma_mle": 1.4, "hst_lower": 1.1,
     "hst_upper": 1.7, "hst_open": "lower", "nfw_median": 1.5, "tnfw_median": 1.3,
     "spearman_rho": 0.9, "n_max": 13, "coverage_nmax": 0.7},
    {"training": "b", "seed": 1, "hst_gamma_mle": 1.8, "hst_lower": 1.5,
     "hst_upper": 2.1, "hst_open": "no", "nfw_median": 1.6, "tnfw_median": 1.4,
     "spearman_rho": 0.85, "n_max": 13, "coverage_nmax": 0.69},
]  # fmt: skip


def test_the_spread_sentence_counts_open_intervals():
    text = seeds_markdown(ROWS)
    assert text.count("\n| ") == 2  # two rows below the header
    assert "spans 1.40–1.80 (0.40, standard deviation 0.28); 1 of 2 intervals are open" in text


def _hst_result(path, mle, lower, upper, lower_at_edge=False, upper_at_edge=False):
    row = {"n_images": 13, "gamma_mle": mle, "lower": lower, "upper": upper,
           "lower_at_edge": lower_at_edge, "upper_at_edge": upper_at_edge}  # fmt: skip
    pd.DataFrame([row]).to_csv(path, index=False)
    return path


def test_the_summary_shows_the_trainings_table_when_it_exists(tmp_path):
    csv = tmp_path / "seeds.csv"
    pd.DataFrame(ROWS).to_csv(csv, index=False)
    text = "".join(seeds_lines(csv))
    assert "| a | derived | 1.40 [1.10, 1.70] | lower |" in text
    assert "| b | 1 | 1.80 [1.50, 2.10] | no |" in text
    assert "spans 1.40–1.80" in text
    assert "`subslope seeds` trains it again" in "".join(seeds_lines(tmp_path / "none.csv"))


@pytest.mark.parametrize(
    "result, seeds, verdict",
    [
        # open at the edge
        ((1.4, 1.1, 1.7, True), False, "its 68% interval is open at a prior edge"),
        # closed, but moves by 0.40 > half-width 0.15 between trainings
        ((2.2, 2.05, 2.35, False), True, "it moves by 0.40 between 2 trainings, more than its"),
        # closed, one training, outside the null range: a measurement
        ((2.2, 2.05, 2.35, False), False, "the 13 lenses read γ = 2.20 [2.05, 2.35] (68%)"),
    ],
)
def test_the_meaning_sentence_names_what_stands_in_the_way(tmp_path, result, seeds, verdict):
    mle, lower, upper, at_edge = result
    hst = _hst_result(tmp_path / "hst.csv", mle, lower, upper, lower_at_edge=at_edge)
    null = tmp_path / "null.csv"
    pd.DataFrame(
        [{"scene": "null_nosub", "n_per_stack": 13, "stack_mle_p16": 1.1, "stack_mle_p84": 1.6}]
    ).to_csv(null, index=False)
    csv = tmp_path / "seeds.csv"
    pd.DataFrame(ROWS).to_csv(csv, index=False)
    text = "".join(meaning_lines(hst, null, csv if seeds else None))
    assert verdict in text
    assert ("not a measurement" in text) == (
        verdict != "the 13 lenses read γ = 2.20 [2.05, 2.35] (68%)"
    )
    assert ("null_nosub [1.10, 1.60]" in text) == (mle < 1.6)


def test_what_the_lenses_could_show_scales_the_signal_budget_to_the_stack(tmp_path):
    hst = _hst_result(tmp_path / "hst.csv", 1.4, 1.1, 1.7)
    signal = tmp_path / "signal.csv"
    pd.DataFrame(
        [
            {"scene": "train", "multiplier": "", "refit_p50": 64.0},
            {"scene": "nfw", "multiplier": 0.5, "refit_p50": 1.0},
            {"scene": "nfw", "multiplier": 1.0, "refit_p50": 4.0},
            {"scene": "tnfw", "multiplier": 1.0, "refit_p50": 1.5},
        ]
    ).to_csv(signal, index=False)
    text = "".join(reach_lines(hst, signal, ("nfw", "tnfw")))
    assert "a Δχ² of 52 (nfw) and 19.5 (tnfw)" in text and "against 832 for 13" in text
    assert reach_lines(hst, None, ("nfw",)) == []
    assert reach_lines(hst, signal, ("other",)) == []


def test_the_workflow_reads_the_table_where_the_command_writes_it():
    from subslope.campaigns import targets

    common = (REPO_ROOT / "workflow" / "rules" / "common.smk").read_text()
    assert "SEEDS_CSV = subslope.campaigns.targets.SEEDS_CSV" in common
    assert targets.SEEDS_CSV == SEEDS_CSV
    command = summary_command(["config/a.yaml", "b.yaml"], snakefile="Snakefile", cores=3,
                              extra=["--rerun-triggers", "mtime"])  # fmt: skip
    assert command[-3:] == ["results/summary.md", "--rerun-triggers", "mtime"]
    assert command[3:8] == ["--configfile", "config/a.yaml", "--configfile", "b.yaml", "--cores"]


def test_one_command_trains_a_seed_on_the_campaigns_shards(tiny_run, tmp_path):
    root = tiny_run.parent
    exe = Path(sys.executable).with_name("subslope")
    command = [str(exe), "seeds", "--config", "config/tiny.yaml", "--seeds", "3",
               "--folder", str(tmp_path), "--cores", "2"]  # fmt: skip
    env = dict(os.environ, OMP_NUM_THREADS="1", SUBSLOPE_DATA_MIRROR=str(shared_data_dir()))
    proc = subprocess.run(command, cwd=root, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-5000:] + proc.stderr[-5000:]
    table = pd.read_csv(tmp_path / "seeds.csv")
    assert list(table.columns) == list(SEEDS_COLUMNS)
    assert table["training"].tolist() == ["tiny", "tiny_seed3"]
    assert table["seed"].astype(str).tolist() == ["derived", "3"]
    own = pd.read_csv(tiny_run / "hst_result.csv").iloc[0]
    assert table["hst_gamma_mle"].iloc[0] == pytest.approx(float(own["gamma_mle"]))
    seed_results = tmp_path / "tiny_seed3" / "results"
    other = pd.read_csv(seed_results / "hst_result.csv").iloc[0]
    assert table["hst_gamma_mle"].iloc[1] == pytest.approx(float(other["gamma_mle"]))
    assert "trainings the combined HST γ_MLE spans" in (tmp_path / "seeds.md").read_text()
    # every shard came from the campaign's cache; the estimator-free stages stayed off
    logs = list((tmp_path / "tiny_seed3" / "logs" / "simulate_shard").rglob("*.log"))
    assert logs and all("taken from the cache" in p.read_text() for p in logs)
    assert not (seed_results / "signal_budget").exists()
    assert not (seed_results / "check_domain").exists()


def test_a_comparison_that_could_not_be_made_is_not_checked(tmp_path):
    """Five lenses against null scenes stacked 13 deep only: no comparison, so the
    sentence says "not checked", never "outside the subhalo-free range"."""
    hst = tmp_path / "hst.csv"
    row = {
        "n_images": 5,
        "gamma_mle": 1.73,
        "lower": 1.47,
        "upper": 2.04,
        "lower_at_edge": False,
        "upper_at_edge": False,
    }
    pd.DataFrame([row]).to_csv(hst, index=False)
    null = tmp_path / "null.csv"
    pd.DataFrame(
        [{"scene": "null_nosub", "n_per_stack": 13, "stack_mle_p16": 1.63, "stack_mle_p84": 1.84}]
    ).to_csv(null, index=False)
    text = "".join(meaning_lines(hst, null))
    assert "not checked" in text and "no subhalo-free null scene is stacked 5 deep" in text
    assert "outside" not in text and "it is a measurement" not in text


def test_the_dense_subhalo_lens_is_named_only_when_it_is_in_the_set(tmp_path):
    from subslope.stages.summary_hst import leave_one_out_lines

    loo = tmp_path / "loo.csv"
    rows = [
        {
            "left_out": f"MINE{k}",
            "mle": 1.7,
            "lower": 1.4,
            "upper": 2.0,
            "shift": 0.01 * k,
            "n_images": 4,
        }
        for k in range(1, 6)
    ]
    pd.DataFrame(rows).to_csv(loo, index=False)
    assert "SDSSJ0946+1006" not in "".join(leave_one_out_lines(loo, ["SDSSJ0946+1006"]))
    rows[0]["left_out"] = "SDSSJ0946+1006"
    pd.DataFrame(rows).to_csv(loo, index=False)
    text = "".join(leave_one_out_lines(loo, ["SDSSJ0946+1006"]))
    assert "highlighted in the config (hst.highlight): SDSSJ0946+1006" in text
    assert "SDSSJ0946+1006 (" not in "".join(leave_one_out_lines(loo))  # only as a row
    assert "highlighted" not in "".join(leave_one_out_lines(loo))
