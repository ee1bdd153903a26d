"""The generated results page (``subslope results-page``): its verdicts follow the CSVs,
and a folder that is not a finished campaign is refused by name."""

from __future__ import annotations

import json

import pytest

from subslope.campaigns.results_page import ResultsPageError, results_page, verdicts
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
    (root / "run.json").write_text(
        json.dumps({"machine": {"cpu": "Test CPU", "cores": 2, "torch": "x"}})
    )
    return root


def test_an_hst_reading_inside_the_null_range_is_called_a_symptom(tmp_path):
    text = " ".join(verdicts(_campaign(tmp_path / "a", hst_mle=1.5)))
    assert "symptom, not a measurement" in text and "ρ = 0.90" in text
    text = " ".join(verdicts(_campaign(tmp_path / "b", hst_mle=2.2)))
    assert "symptom" not in text and "outside the 16–84% range" in text


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
