"""The documents' three homes: a short front page, reference pages without experiment
records or commit hashes, an index for every script folder and for the notebook."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.conftest import REPO_ROOT

DOCS = REPO_ROOT / "docs"
#: A commit hash, short or full, or a config hash: 7–40 hexadecimal digits with a digit
#: and a letter (a SHA-256 sum, 64 digits, is data, not provenance).
HASH = re.compile(
    r"(?<![.\w])(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b(?![-+]\d)"
)  # not the digits of a number such as 3.516773369438426e-47


def _reference_documents():
    pages = [REPO_ROOT / "README.md", REPO_ROOT / "CONTRIBUTING.md"]
    return pages + [p for p in sorted(DOCS.rglob("*.md")) if "notebook" not in p.parts]


@pytest.mark.parametrize("path", _reference_documents(), ids=lambda p: p.name)
def test_no_commit_hash_outside_the_notebook(path):
    hits = [
        f"{path.name}:{n}: {m}"
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        for m in HASH.findall(line)
    ]
    assert not hits, "commit hashes belong in docs/notebook/:\n" + "\n".join(hits)


def test_hash_pattern_finds_commits_and_spares_config_hashes():
    assert HASH.findall("at 0a6ce62, full 14e2df2") == ["0a6ce62", "14e2df2"]
    assert HASH.findall("config hash `811bc79c399275f3`") == ["811bc79c399275f3"]
    assert not HASH.findall(
        "a sha256 " + "ab12" * 16 + ", a word deadbeef, p = 3.516773369438426e-47"
    )


def test_readme_is_a_front_page():
    text = (REPO_ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 120
    assert "docs/results.md" in text and "docs/index.md" in text
    assert "bash scripts/setup_env.sh && .venv/bin/snakemake --cores 2" in text
    assert "bash scripts/setup_env.sh && .venv/bin/python -m pytest" in text


@pytest.mark.parametrize("folder", ["benchmarks", "studies"])
def test_every_script_is_in_its_folder_index(folder):
    index = (REPO_ROOT / folder / "README.md").read_text(encoding="utf-8")
    scripts = [
        p.name
        for p in sorted((REPO_ROOT / folder).iterdir())
        if p.suffix in (".py", ".sh") and not p.name.startswith("_")
    ]
    assert scripts
    missing = [name for name in scripts if f"`{name}`" not in index]
    assert not missing, f"{folder}/README.md does not list {missing}"


def test_notebook_entries_are_dated_and_listed():
    notebook = DOCS / "notebook"
    index = (notebook / "README.md").read_text(encoding="utf-8")
    entries = sorted(p.name for p in notebook.glob("*.md") if p.name != "README.md")
    assert entries
    bad = [e for e in entries if not re.match(r"\d{4}-\d\d-\d\d-[a-z0-9-]+\.md$", e)]
    assert not bad, bad
    missing = [e for e in entries if f"({e})" not in index]
    assert not missing, f"docs/notebook/README.md does not list {missing}"
    for entry in entries:
        first = (notebook / entry).read_text(encoding="utf-8").splitlines()[0]
        assert first.startswith(f"# {entry[:10]}: "), (entry, first)


def test_index_names_every_page():
    index = (DOCS / "index.md").read_text(encoding="utf-8")
    pages = [p.name for p in DOCS.glob("*.md") if p.name != "index.md"]
    missing = [p for p in pages if f"({p})" not in index]
    assert not missing, f"docs/index.md does not link {missing}"


def _pointer_sources() -> list[Path]:
    """Where the project points a reader: config comments, the workflow's headers and
    rules, the reference pages, the front page (not the notebook's dated records)."""
    return [
        *sorted((REPO_ROOT / "config").rglob("*.yaml")),
        REPO_ROOT / "Snakefile",
        *sorted((REPO_ROOT / "workflow" / "rules").glob("*.smk")),
        *sorted((REPO_ROOT / "docs").glob("*.md")),
        REPO_ROOT / "README.md",
    ]


def test_every_docs_path_and_stage_named_exists():
    from subslope.config import STAGE_NEEDS

    stages = set(STAGE_NEEDS) | {"data"}
    missing = []
    for path in _pointer_sources():
        text = path.read_text(encoding="utf-8")
        for m in re.finditer(r"(?<![\w/.])docs/[\w./-]*\w", text):
            if not (REPO_ROOT / m.group(0)).exists():
                missing.append(f"{path.relative_to(REPO_ROOT)}: {m.group(0)}")
        for m in re.finditer(r"stage `(\w+)`", text):
            if m.group(1) not in stages:
                missing.append(f"{path.relative_to(REPO_ROOT)}: stage `{m.group(1)}`")
    assert not missing, "\n".join(missing)


def test_the_citation_file_carries_the_package_version():
    import yaml

    from subslope import __version__

    cff = yaml.safe_load((REPO_ROOT / "CITATION.cff").read_text(encoding="utf-8"))
    assert cff["version"] == __version__ and "arXiv:2308.09739" in str(cff)


def test_the_readme_states_the_results_page_verdicts():
    """The front page's current result and the generated results page's verdicts agree:
    the same stack ρ, coverage, halo-free verdict, figure-4 verdicts and HST reading."""
    readme = (REPO_ROOT / "README.md").read_text(encoding="utf-8")
    result = " ".join(readme.split("## The current result", 1)[1].split("\n## ", 1)[0].split())
    page = (DOCS / "results.md").read_text(encoding="utf-8")
    verdict = " ".join(page.split("## Verdict", 1)[1].split("\n## ", 1)[0].split())
    rho = re.search(r"Spearman ρ = (\d\.\d+)", verdict).group(1)
    assert f"ρ {rho}" in result
    assert "within 2σ of the level at every N" in verdict and "coverage within 2σ" in result
    assert "(halo-free null test passes)" in verdict and "halo-free null test passes" in result
    assert "no reading maps to a slope" in verdict and "maps to a slope**" in result
    assert "not settled" in verdict and "**not settled**" in result
    hst = re.search(r"read γ_MLE = (\d\.\d+), 68% interval \[(\d\.\d+), (\d\.\d+)\]", verdict)
    assert f"γ_MLE = {hst.group(1)} [{hst.group(2)}, {hst.group(3)}]" in result
    null_range = "inside the 16–84% range of the 13-image stacks of the subhalo-free scenes"
    assert null_range in verdict and "**a symptom, not a measurement of γ**" in result
