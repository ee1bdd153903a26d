"""Shard files: layout, atomic writing, byte-identical output, validation errors."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from subslope.io import shards


def _write(path, seed=0, n=4, attrs=None, **kw):
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
        attrs={"scene": "train", "scene_spec": {"a": [1, 2]}, "config_hash": "x", **(attrs or {})},
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


def test_a_shard_copied_over_another_is_refused_by_every_reader(tmp_path):
    """In the workflow's shard folder a shard must be the one its path names: scene,
    index and multiplier (what ``cp shard_1.h5 shard_0.h5`` breaks)."""
    root = tmp_path / "results" / shards.WORKFLOW_SHARD_FOLDER
    one = _write(root / "train" / "shard_1.h5", attrs={"shard_index": 1, "multiplier": None})
    zero = root / "train" / "shard_0.h5"
    zero.write_bytes(one.read_bytes())
    with pytest.raises(shards.ShardError, match=r"shard_0.h5 is not the shard its path names"):
        shards.open_shard(zero)
    with pytest.raises(shards.ShardError, match=r"shard_index '1' \(its path: '0'\)"):
        shards.verify_shard(zero)
    shards.open_shard(one).close()
    cdm = _write(root / "nfw" / "a8" / "shard_0.h5", attrs={"scene": "nfw", "shard_index": 0,
                                                          "multiplier": 8.0})  # fmt: skip
    (root / "nfw" / "a1").mkdir()
    moved = root / "nfw" / "a1" / "shard_0.h5"
    moved.write_bytes(cdm.read_bytes())
    with pytest.raises(shards.ShardError, match=r"multiplier '8' \(its path: '1'\)"):
        shards.open_shard(moved)
    other = root / "tnfw" / "a8" / "shard_0.h5"
    other.parent.mkdir(parents=True)
    other.write_bytes(cdm.read_bytes())
    with pytest.raises(shards.ShardError, match=r"scene 'nfw' \(its path: 'tnfw'\)"):
        shards.open_shard(other)
    from subslope.plan import SHARD_DIR, shard_path

    assert SHARD_DIR.split("/")[-1] == shards.WORKFLOW_SHARD_FOLDER
    assert shard_path("nfw", 0, 8.0, root=str(root)) == str(root / "nfw" / "a8" / "shard_0.h5")
    # outside the workflow's folder a shard is not held to its name
    outside = tmp_path / "kept" / "shard_0.h5"
    outside.parent.mkdir()
    outside.write_bytes(one.read_bytes())
    shards.open_shard(outside).close()


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
