"""The CDM visibility check (subslope.stages.null_tests.visibility): the paired shift of the stack
γ_MLE when the subhalos are removed, its test, and the pairing of the profiles files."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from subslope.io.ratio_profiles import write_profiles
from subslope.stages.null_tests.visibility import (
    VISIBILITY_COLUMNS,
    cdm_visibility,
    paired_stack_mles,
    visibility_row,
)
from subslope.stats.intervals import gamma_grid

GRID = gamma_grid(1.1, 2.9, 181)


def test_a_shift_of_every_set_is_visible_and_measured():
    rng = np.random.default_rng(3)
    without = rng.uniform(1.1, 2.0, 40)
    row = visibility_row("nfw", without + 0.1, without)
    assert set(row) == set(VISIBILITY_COLUMNS)
    assert row["visible"] and row["wilcoxon_p"] < 1e-6 and row["moved"] == 1.0
    assert row["shift_mean"] == pytest.approx(0.1) and row["shift_mean_se"] == pytest.approx(0)
    assert row["stack_mle_p50"] == pytest.approx(np.median(without) + 0.1)


def test_unmoved_and_symmetrically_scattered_sets_are_not_visible():
    rng = np.random.default_rng(4)
    without = rng.uniform(1.1, 2.9, 40)
    same = visibility_row("tnfw", without, without)
    assert same["wilcoxon_p"] == 1.0 and not same["visible"] and same["moved"] == 0.0
    scatter = rng.normal(0.0, 0.05, 40)
    noisy = visibility_row("tnfw", without + scatter - np.median(scatter), without)
    assert not noisy["visible"] and abs(noisy["shift_p50"]) < 1e-12


def _profiles(path, peaks, sets, theta_e):
    """One profile per image peaking at ``peaks`` (a parabola in γ)."""
    lr = -((GRID[None, :] - np.asarray(peaks)[:, None]) ** 2) / 0.02
    return write_profiles(
        path,
        log_ratio=lr,
        gammas=GRID,
        set_index=sets,
        theta_e=theta_e,
        lens_x=np.zeros(len(sets)),
        lens_y=np.zeros(len(sets)),
    )


def test_files_pair_set_by_set_and_a_mismatch_is_refused(tmp_path):
    sets = np.repeat(np.arange(4), 3)
    te = np.full(12, 1.2)
    orig = _profiles(tmp_path / "o.h5", np.repeat([1.5, 1.8, 2.0, 2.4], 3), sets, te)
    removed = _profiles(tmp_path / "r.h5", np.repeat([1.3, 1.8, 1.9, 2.4], 3), sets, te)
    with_sub, without = paired_stack_mles([orig], [removed])
    np.testing.assert_allclose(with_sub, [1.5, 1.8, 2.0, 2.4], atol=1e-9)
    np.testing.assert_allclose(without, [1.3, 1.8, 1.9, 2.4], atol=1e-9)
    table = cdm_visibility({"nfw": ([orig], [removed])}, tmp_path / "v.csv")
    assert list(pd.read_csv(tmp_path / "v.csv").columns) == list(VISIBILITY_COLUMNS)
    assert table.loc[0, "moved"] == 0.5 and table.loc[0, "shift_mean"] == pytest.approx(0.075)
    other = _profiles(tmp_path / "x.h5", np.repeat([1.3, 1.8, 1.9, 2.4], 3), sets, te * 1.1)
    with pytest.raises(ValueError, match="theta_e differs"):
        paired_stack_mles([orig], [other])
