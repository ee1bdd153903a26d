"""Shard files: layout, atomic writing, byte-identical output, validation errors."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from subslope.io import shards


def _write(path, seed=0, n=4, **kw):
    rng = np.random.default_rng(seed)
    params = {k: rng.random(n) for k in ("theta_e", "lens_x", "lens_y", "gamma_sub")}
    params["set_index"] = np.arange(n)
    params["noise_seed"] = rng.integers(0, 2**63, n).astype(np.uint64)
    counts = rng.integers(0, 3, n)
    return shards.write_shard(
        path,
        images=rng.normal(size=(n, 20, 20)),
        params=params,
        psf=np.ones((3, 3)) / 9,
        subhalos={"counts": counts, "x": rng.random(counts.sum())},
        los={"counts": np.zeros(n, np.int64)},
        sources={"ident": np.arange(n)},
        attrs={"scene": "train", "scene_spec": {"a": [1, 2]}, "config_hash": "x"},
        **kw,
    )


def test_layout_and_roundtrip(tmp_path):
    path = _write(tmp_path / "s.h5")
    with shards.open_shard(path) as s:
        assert (
            len(s) == 4 and s.images.dtype == np.float32 and s.images.dataset.chunks == (1, 20, 20)
        )
        assert s.images.dataset.fletcher32 and s.file["params/gamma_sub"].fletcher32
        assert s.images.compression == "gzip" and s.images.shuffle
        assert s.attrs["format"] == shards.FORMAT_NAME and s.attrs["complete"] is True
        assert s.attrs["scene_spec"] == {"a": [1, 2]}
        assert s.params["theta_e"].dtype == np.float64 and s.params["set_index"].dtype == np.int64
        assert s.params["noise_seed"].dtype == np.uint64
        sub = s.ragged("subhalos", [1, 3])
        off = np.concatenate([[0], np.cumsum(s.subhalos["counts"])])
        x = s.subhalos["x"]
        np.testing.assert_array_equal(
            sub["x"], np.concatenate([x[off[1] : off[2]], x[off[3] : off[4]]])
        )
    assert not list(tmp_path.glob("*.tmp-*"))


def test_same_input_byte_identical_file(tmp_path):
    a, b = _write(tmp_path / "a.h5"), _write(tmp_path / "b.h5")
    assert shards.file_sha256(a) == shards.file_sha256(b)
    c = _write(tmp_path / "c.h5", seed=1)
    assert shards.file_sha256(a) != shards.file_sha256(c)


def test_refuses_to_overwrite(tmp_path):
    path = _write(tmp_path / "s.h5")
    before = shards.file_sha256(path)
    with pytest.raises(FileExistsError, match="s.h5"):
        _write(path, seed=3)
    assert shards.file_sha256(path) == before
    _write(path, seed=3, overwrite=True)
    assert shards.file_sha256(path) != before


def test_truncated_file(tmp_path):
    path = _write(tmp_path / "s.h5")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(shards.ShardError, match="s.h5"):
        shards.open_shard(path)


def test_incomplete_file(tmp_path):
    path = _write(tmp_path / "s.h5")
    with h5py.File(path, "r+") as f:
        del f.attrs["complete"]
    with pytest.raises(shards.ShardError, match=r"s\.h5 is incomplete"):
        shards.open_shard(path)


def test_foreign_and_old_files(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f["images"] = np.zeros((1, 2, 2))
        f.attrs["format"] = "lampe"
    with pytest.raises(shards.ShardError, match=r"other\.h5 is not a subslope shard"):
        shards.open_shard(path)
    path = _write(tmp_path / "s.h5")
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = 99
    with pytest.raises(shards.ShardError, match="version 99"):
        shards.open_shard(path)
    path = _write(tmp_path / "t.h5")
    with h5py.File(path, "r+") as f:
        del f["params/theta_e"]
    with pytest.raises(shards.ShardError, match="params/theta_e"):
        shards.open_shard(path)
    (tmp_path / "text.h5").write_text("not hdf5")
    with pytest.raises(shards.ShardError, match="text.h5"):
        shards.open_shard(tmp_path / "text.h5")
    with pytest.raises(shards.ShardError, match="missing.h5"):
        shards.open_shard(tmp_path / "missing.h5")


def test_write_validates_shapes(tmp_path):
    with pytest.raises(shards.ShardError, match="subhalos/x"):
        shards.write_shard(
            tmp_path / "bad.h5",
            images=np.zeros((2, 4, 4)),
            params={
                k: np.zeros(2) for k in ("theta_e", "lens_x", "lens_y", "set_index", "noise_seed")
            },
            psf=np.ones((1, 1)),
            subhalos={"counts": np.array([1, 1]), "x": np.zeros(3)},
            los={"counts": np.zeros(2)},
            attrs={},
        )
    assert not list(tmp_path.iterdir())
