"""benchmarks/compare_runs.py: the check that a refactoring changed no number finds a
single changed value, and ignores only what it documents."""

from __future__ import annotations

import importlib.util
import json

import h5py
import numpy as np

from tests.conftest import REPO_ROOT


def _module():
    spec = importlib.util.spec_from_file_location(
        "compare_runs", REPO_ROOT / "benchmarks" / "compare_runs.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _results(root, value=1.0, version="a", digest="x"):
    (root / "shards").mkdir(parents=True)
    with h5py.File(root / "shards" / "s.h5", "w") as fh:
        fh.create_dataset("images", data=np.array([[0.5, value]], dtype=np.float32))
        fh.attrs["package_version"] = version
        fh.attrs["scene"] = "train"
    (root / "w.json").write_text(
        json.dumps({"mean": 0.25, "shards": [{"path": "s.h5", "sha256": digest}]})
    )
    (root / "summary.md").write_text("# summary\n## HST measurement\nγ = 2.000 (68% [1.9, 2.1])\n")
    return root


def test_identical_runs_pass_and_layout_attributes_are_ignored(tmp_path):
    cr = _module()
    a = _results(tmp_path / "a")
    b = _results(tmp_path / "b", version="b", digest="y")
    assert cr.compare_trees(a, b) == 0


def test_one_changed_value_is_found(tmp_path, capsys):
    cr = _module()
    a = _results(tmp_path / "a")
    b = _results(tmp_path / "b", value=np.nextafter(np.float32(1.0), np.float32(2.0)))
    assert cr.compare_trees(a, b) == 1
    assert "dataset images differs" in capsys.readouterr().out


def test_a_changed_summary_number_and_a_missing_file_are_found(tmp_path):
    cr = _module()
    a = _results(tmp_path / "a")
    b = _results(tmp_path / "b")
    (b / "summary.md").write_text("# summary\n## HST measurement\nγ = 2.001 (68% [1.9, 2.1])\n")
    (b / "w.json").unlink()
    assert cr.compare_trees(a, b) == 2
