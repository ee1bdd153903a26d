"""subslope.campaigns.compare (``subslope compare-runs``): the check that a refactoring
changed no number finds a single changed value, and ignores only what it documents."""

from __future__ import annotations

import json

import h5py
import numpy as np

from subslope.campaigns import compare


def _module():
    return compare


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


class _Payload:
    """Pickles to a call that writes a marker file: code a model file must never run."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_a_model_file_with_a_pickle_payload_runs_no_code(tmp_path):
    import torch

    marker = tmp_path / "ran"
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        torch.save({"model_state": {}, "extra": _Payload(marker)}, tmp_path / name / "model.pt")
    assert compare.compare_trees(tmp_path / "a", tmp_path / "b") == 1
    assert not marker.exists()
