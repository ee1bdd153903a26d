"""Whitening statistics: streaming Chan/Welford reduction over shards vs numpy."""

from __future__ import annotations

import json

import numpy as np
import pytest

from subslope.io import shards
from subslope.nre import whitening


def _shard(path, images):
    n = images.shape[0]
    params = {k: np.zeros(n) for k in ("theta_e", "lens_x", "lens_y")}
    params.update(set_index=np.arange(n), noise_seed=np.arange(n, dtype=np.uint64))
    return shards.write_shard(
        path,
        images=images,
        params=params,
        psf=np.ones((1, 1)),
        subhalos={"counts": np.zeros(n, np.int64)},
        los={"counts": np.zeros(n, np.int64)},
        attrs={"scene": "train"},
    )


def test_matches_numpy_on_concatenation(tmp_path):
    rng = np.random.default_rng(5)
    parts = [(1e3 + 7.0 * rng.standard_normal((n, 12, 12))).astype(np.float32) for n in (5, 1, 9)]
    paths = [_shard(tmp_path / f"s{k}.h5", p) for k, p in enumerate(parts)]
    allpix = np.concatenate(parts).astype(np.float64)
    for chunk in (1, 4, 256):
        m = whitening.pixel_statistics(paths, chunk_images=chunk)
        assert m.n == allpix.size
        assert m.mean == pytest.approx(allpix.mean(), rel=1e-13)
        assert m.std == pytest.approx(allpix.std(), rel=1e-10)
    out = tmp_path / "w" / "whitening.json"
    res = whitening.compute_whitening(paths, out)
    on_disk = json.loads(out.read_text())
    assert on_disk == json.loads(json.dumps(res))
    assert on_disk["n_images"] == 15 and [s["path"] for s in on_disk["shards"]] == [
        str(p) for p in paths
    ]
    assert on_disk["shards"][0]["sha256"] == shards.file_sha256(paths[0])
    assert on_disk["shards"][0]["bytes"] == paths[0].stat().st_size
    assert whitening.load_whitening(out) == (res["mean"], res["std"])


def test_merge_is_exact_for_disjoint_parts():
    rng = np.random.default_rng(0)
    a, b = rng.normal(3, 2, 1000), rng.normal(-1, 0.5, 17)
    m = whitening.Moments.of(a).merge(whitening.Moments.of(b))
    both = np.concatenate([a, b])
    assert m.mean == pytest.approx(both.mean(), rel=1e-14) and m.var == pytest.approx(
        both.var(), rel=1e-12
    )
    assert whitening.Moments().merge(m) == m and m.merge(whitening.Moments()) == m


def test_rejects_empty_and_bad_input(tmp_path):
    with pytest.raises(ValueError, match="at least one shard"):
        whitening.compute_whitening([], tmp_path / "w.json")
    (tmp_path / "junk.h5").write_text("x")
    with pytest.raises(shards.ShardError, match="junk.h5"):
        whitening.pixel_statistics([tmp_path / "junk.h5"])
