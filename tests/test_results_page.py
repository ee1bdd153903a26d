"""The generated results page (``subslope results-page``): its verdicts follow the CSVs,
and a folder that is not a finished campaign is refused by name."""

from __future__ import annotations

import csv
import json

import pytest

from subslope.campaigns.results_page import (
    SUMMARY_TABLES,
    ResultsPageError,
    results_page,
    verdicts,
)
from subslope.cli import main

SUMMARY = """# subslope campaign summary: `reduced`

## Configuration

- run_name: `reduced`
- config hash: `abc123`
- config file(s): `config/config.yaml`

## HST measurement

Combined stack of 13 HST lenses: γ_MLE = 1.500.
"""


def _campaign(root, hst_mle=1.5, overconfident="False"):
    root.mkdir()
    (root / "summary.md").write_text(SUMMARY)
    (root / "hst_result.csv").write_text(
        "n_images,gamma_mle,lower,upper,lower_at_edge,upper_at_edge\n"
        f"13,{hst_mle},1.2,1.8,False,False\n"
    )
    (root / "null_tests.csv").write_text(
        "scene,stack_mle_p16,stack_mle_p84,n_per_stack\nnull_nosub,1.4,1.6,13\n"
    )
    (root / "coverage.csv").write_text(f"n_images,overconfident\n1,False\n13,{overconfident}\n")
    (root / "trend.csv").write_text("rho,p_value,n\n0.9,1e-10,400\n")
    (root / "halo_free.csv").write_text(
        "variant,n_stacks,rho_stack,passes\noriginal,20,0.9,\nsheets_removed,20,0.01,True\n"
    )
    for name, header in (
        ("cdm_prediction.csv", "scene,median,p16,p84,n_sets"),
        ("cdm_visibility.csv", "scene,multiplier,visible,shift_mean,shift_mean_se"),
        ("figure4.csv", "grid,nfw_scene,verdict"),
    ):
        (root / name).write_text(header + "\n")  # stage off: header only
    (root / "run.json").write_text(
        json.dumps({"machine": {"cpu": "Test CPU", "cores": 2, "torch": "x"}})
    )
    return root


def test_an_hst_reading_inside_the_null_range_is_called_a_symptom(tmp_path):
    text = " ".join(verdicts(_campaign(tmp_path / "a", hst_mle=1.5)))
    assert "symptom, not a measurement" in text and "ρ = 0.90" in text
    text = " ".join(verdicts(_campaign(tmp_path / "b", hst_mle=2.2)))
    assert "symptom" not in text and "outside the 16–84% range" in text


def test_a_complete_folder_reads_every_table(tmp_path):
    root = _campaign(tmp_path / "a")
    assert {p.name for p in root.glob("*.csv")} >= set(SUMMARY_TABLES)
    text = " ".join(verdicts(root))
    assert "not read" not in text and "not checked" not in text
    assert "halo-free null test passes" in text


def test_a_table_missing_or_cut_short_is_named_and_its_caveat_kept(tmp_path):
    root = _campaign(tmp_path / "a", hst_mle=1.5)
    (root / "null_tests.csv").unlink()
    text = " ".join(verdicts(root))
    assert "Not checked against the subhalo-free null stacks" in text
    assert "not a measurement of γ" in text
    assert "Tables not read**: null_tests.csv (missing)" in text
    root = _campaign(tmp_path / "b")
    halo = root / "halo_free.csv"
    halo.write_text(halo.read_text()[:-12])  # a file cut short mid-row
    text = " ".join(verdicts(root))
    assert "halo-free null test: not checked" in text and "passes" not in text
    assert "halo_free.csv (unreadable: line 3 has not 4 fields)" in text
    (root / "coverage.csv").unlink()
    assert "Held-out coverage: not checked" in " ".join(verdicts(root))


def test_an_observation_set_deeper_than_the_null_stacks_is_not_checked(tmp_path):
    root = _campaign(tmp_path / "a")
    (root / "hst_result.csv").write_text(
        "n_images,gamma_mle,lower,upper,lower_at_edge,upper_at_edge\n5,1.73,1.47,2.04,False,False\n"
    )
    text = " ".join(verdicts(root))
    assert "no null scene is stacked 5 deep" in text and "outside" not in text


def test_overconfident_stack_sizes_are_named(tmp_path):
    text = " ".join(verdicts(_campaign(tmp_path / "a", overconfident="True")))
    assert "more than 2σ below 68% at N = 13" in text


def test_page_states_command_machine_and_carries_the_summary(tmp_path):
    page = results_page(_campaign(tmp_path / "a"))
    assert "`snakemake --cores 2`" in page and "Test CPU, 2 cores, no GPU" in page
    assert "abc123" not in page and "### HST measurement" in page


def test_cli_refuses_a_folder_without_a_summary(tmp_path, capsys):
    assert main(["results-page", str(tmp_path), "--out", str(tmp_path / "r.md")]) == 1
    assert f"{tmp_path / 'summary.md'} not found" in capsys.readouterr().err
    with pytest.raises(ResultsPageError):
        results_page(tmp_path)


def test_seeds_and_reference_curve_reach_the_page(tmp_path):
    root = tmp_path / "r"
    _campaign(root)
    (root / "measure_cdm_grid").mkdir()
    (root / "measure_cdm_grid" / "cdm_grid.csv").write_text(
        "scene,multiplier,n_sets,n_images,median,lo,hi,reference,distance\n"
        "nfw,1.0,40,13,1.53,1.1,1.64,1.71,-0.18\n"
    )
    assert not any("trainings" in v for v in verdicts(root))
    (root / "seeds").mkdir()
    (root / "seeds" / "seeds.csv").write_text(
        "training,seed,hst_gamma_mle,hst_lower,hst_upper,hst_open\n"
        "reduced,derived,1.41,1.10,1.72,lower\nreduced_seed1,1,1.79,1.49,2.15,no\n"
    )
    (root / "seeds" / "seeds.md").write_text("| training |\n|---|\n| reduced |\n")
    found = verdicts(root)
    assert any("nfw a = 1 1.53 against 1.71" in v for v in found)
    assert any("spans 1.41–1.79; 1 of 2 intervals are open" in v for v in found)
    assert "## Training seeds" in results_page(root)


def test_the_summary_and_the_page_give_the_halo_free_test_one_verdict(tmp_path):
    """One function decides (sheets_removed is the criterion; failing with the sheets
    kept is what the sheets carry): the summary's section and the page agree."""
    from subslope.stages.null_tests.halo_free import halo_free_verdict
    from subslope.stages.summary import write_summary

    root = _campaign(tmp_path / "a")
    (root / "halo_free.csv").write_text(
        "variant,n_images,n_stacks,rho_single,rho_single_p,rho_stack,passes\n"
        "original,26,20,0.4,0.001,0.9,\nsheets_kept,26,20,0.2,0.01,0.25,False\n"
        "sheets_removed,26,20,0.0,0.9,-0.02,True\n"
    )
    rows = list(csv.DictReader(open(root / "halo_free.csv", encoding="utf-8")))
    verdict = halo_free_verdict(rows)
    assert verdict["passes"] and verdict["sheets_carry"] and not verdict["uninformative"]
    page = " ".join(verdicts(root))
    assert "halo-free null test passes" in page and "not a failure of the test" in page
    bias = tmp_path / "bias.csv"
    from subslope.stages.null_tests.halo_free import BIAS_COLUMNS

    bias.write_text(",".join(BIAS_COLUMNS) + "\n" + ",".join(["1"] * len(BIAS_COLUMNS)) + "\n")
    out = tmp_path / "s" / "summary.md"
    write_summary(
        out, run_name="t", config_hash="x", halo_free_csv=root / "halo_free.csv", bias_csv=bias
    )
    section = out.read_text(encoding="utf-8")
    assert "**passes**" in section and "**fails**" not in section
    assert "sheets kept the γ_MLE still follows the label" in section
