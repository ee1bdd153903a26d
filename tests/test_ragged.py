"""Tests of subslope.ragged: flat members + counts <-> offsets <-> padded arrays."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from subslope.ragged import counts_to_offsets, counts_to_starts, pack_ragged, unpack_ragged


def test_ragged_round_trip(rng):
    counts = np.array([3, 0, 5, 1])
    vals = rng.normal(size=counts.sum())
    padded, mask = pack_ragged(vals, counts=counts, fill=-7.0)
    assert padded.shape == (4, 5) and mask.sum() == counts.sum()
    assert np.all(padded[~mask] == -7.0)
    np.testing.assert_array_equal(padded[2, :5], vals[3:8])
    flat, c2 = unpack_ragged(padded, mask)
    np.testing.assert_array_equal(flat, vals)
    np.testing.assert_array_equal(c2, counts)
    p2, m2 = pack_ragged(vals, offsets=counts_to_offsets(counts), n_max=7)
    assert p2.shape == (4, 7)
    np.testing.assert_array_equal(unpack_ragged(torch.as_tensor(p2), torch.as_tensor(m2))[0], vals)
    vec = rng.normal(size=(counts.sum(), 2))  # vector-valued members
    pv, mv = pack_ragged(vec, counts=counts)
    np.testing.assert_array_equal(unpack_ragged(pv, mv)[0], vec)
    with pytest.raises(ValueError, match="counts"):
        pack_ragged(vals, counts=counts + 1)
    with pytest.raises(ValueError, match="offsets"):
        pack_ragged(vals, offsets=np.array([1, 2]))


def test_offsets_and_starts():
    counts = np.array([2, 0, 3])
    np.testing.assert_array_equal(counts_to_offsets(counts), [0, 2, 2, 5])
    np.testing.assert_array_equal(counts_to_starts(counts), [0, 2, 2])
    assert counts_to_offsets(np.array([], dtype=int)).tolist() == [0]
    with pytest.raises(ValueError, match="non-negative"):
        counts_to_offsets(np.array([1, -1]))
