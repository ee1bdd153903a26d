"""Pre-processing (whitening + mask) and the streaming shard dataset."""

from __future__ import annotations

import json
import pickle

import h5py
import numpy as np
import pytest
import torch

from subslope.nre.data import ShardBatches, make_loader, read_labels
from subslope.nre.preprocess import preprocess, read_whitening


def write_shard(path, n, seed, *, hw=100, offset=0, complete=True, signal=0.0):
    """Synthetic shard in the layout of subslope.io.shards.

    Pixel [0, 0] of image k holds ``offset + k`` so tests can check which row was read;
    with ``signal`` the image mean carries γ (a learnable toy signal).
    """
    r = np.random.default_rng(seed)
    gamma = r.uniform(1.1, 2.9, n)
    images = r.normal(5.0, 2.0, size=(n, hw, hw)) + signal * gamma[:, None, None]
    images[:, 0, 0] = offset + np.arange(n)
    with h5py.File(path, "w") as fh:
        fh.create_dataset("images", data=images.astype(np.float32), chunks=(min(n, 16), hw, hw))
        fh["params/gamma_sub"] = gamma
        fh["params/theta_e"] = r.uniform(0.9, 1.3, n)
        fh["params/lens_x"] = r.uniform(-0.2, 0.2, n)
        fh["params/lens_y"] = r.uniform(-0.2, 0.2, n)
        fh.attrs["complete"] = complete
    return path


# --- preprocess ----------------------------------------------------------------------
def _reference(images, theta_e, lx, ly, mean, std, scale, factor):
    """Pixel-by-pixel numpy reference."""
    out = np.empty(images.shape, dtype=np.float64)
    b, h, w = images.shape
    for k in range(b):
        for j in range(h):
            for i in range(w):
                x, y = (i - (w - 1) / 2) * scale, (j - (h - 1) / 2) * scale
                inside = (x - lx[k]) ** 2 + (y - ly[k]) ** 2 <= (factor * theta_e[k]) ** 2
                out[k, j, i] = (images[k, j, i] - mean) / std if inside else 0.0
    return out


def test_preprocess_hand_made_mask():
    img = np.full((5, 5), 3.0)
    # unit pixels, θ_E = 1 → radius 1.5 about the centre: the central 3×3 block
    out = preprocess(img, 1.0, 0.0, 0.0, 1.0, 2.0, pixel_scale=1.0)
    expected = np.zeros((5, 5))
    expected[1:4, 1:4] = 1.0  # (3 − 1) / 2
    np.testing.assert_array_equal(out, expected)
    # lens moved one pixel right (+x = +column) and one up (+y = +row)
    out = preprocess(img, 1.0, 1.0, 1.0, 1.0, 2.0, pixel_scale=1.0)
    np.testing.assert_array_equal(out, np.roll(expected, (1, 1), axis=(0, 1)))
    # even grid: 4×4 pixels of 0.04", centres at ±0.02, ±0.06; radius 1.5·0.03 = 0.045
    out = preprocess(np.ones((4, 4)), 0.03, 0.0, 0.0, 0.0, 1.0)
    expected = np.zeros((4, 4))
    expected[1:3, 1:3] = 1.0
    np.testing.assert_array_equal(out, expected)
    # no mask: whitening only
    np.testing.assert_allclose(
        preprocess(img, 1.0, 0, 0, 1.0, 2.0, mask_factor=None), np.ones((5, 5))
    )


def test_preprocess_matches_numpy_reference(rng):
    images = rng.normal(3.0, 2.0, size=(4, 12, 10)).astype(np.float32)
    te, lx, ly = rng.uniform(0.1, 0.2, 4), rng.uniform(-0.05, 0.05, 4), rng.uniform(-0.05, 0.05, 4)
    ref = _reference(images, te, lx, ly, 3.0, 2.0, 0.04, 1.5)
    out = preprocess(images, te, lx, ly, 3.0, 2.0)
    assert isinstance(out, np.ndarray) and out.dtype == np.float32 and out.shape == images.shape
    np.testing.assert_allclose(out, ref, atol=1e-6)
    assert 0 < (out == 0).mean() < 1  # the mask does something
    # torch in → torch out, (B, 1, H, W) with (B,) parameters, float64 kept
    t = preprocess(
        torch.from_numpy(images.astype(np.float64))[:, None], torch.from_numpy(te), lx, ly, 3.0, 2.0
    )
    assert isinstance(t, torch.Tensor) and t.dtype == torch.float64 and t.shape == (4, 1, 12, 10)
    np.testing.assert_allclose(t[:, 0].numpy(), ref, atol=1e-12)
    assert preprocess(np.ones((3, 3), dtype=np.int32), 1, 0, 0, 0, 1).dtype == np.float32


def test_preprocess_bad_input():
    with pytest.raises(ValueError, match="std"):
        preprocess(np.ones((3, 3)), 1, 0, 0, 0.0, 0.0)
    with pytest.raises(ValueError, match="images"):
        preprocess(np.ones(3), 1, 0, 0, 0.0, 1.0)


def test_read_whitening(tmp_path):
    p = tmp_path / "w.json"
    p.write_text(json.dumps({"mean": 1.5, "std": 2.0}))
    assert (
        read_whitening(p)
        == (1.5, 2.0)
        == read_whitening({"mean": 1.5, "std": 2})
        == read_whitening((1.5, 2.0))
    )
    p.write_text(json.dumps({"mean": 1.5}))
    with pytest.raises(ValueError, match="std"):
        read_whitening(p)
    with pytest.raises(ValueError, match="std > 0"):
        read_whitening((0.0, -1.0))
    p.write_text(
        json.dumps({"format": "subslope-whitening", "mean": 2.0, "std": 4.0, "n_images": 10})
    )
    assert read_whitening(p) == (2.0, 4.0)  # extra keys of subslope.nre.whitening files are ignored


# --- streaming dataset ---------------------------------------------------------------
@pytest.fixture
def shards(tmp_path):
    sizes = (37, 50, 13)
    paths, off = [], 0
    for s, n in enumerate(sizes):
        paths.append(write_shard(tmp_path / f"s{s}.h5", n, s, hw=8, offset=off))
        off += n
    return paths, sum(sizes)


def _epoch_indices(ds, workers, start=0):
    out = []
    for batch in make_loader(ds, num_workers=workers, start=start):
        # pixel [0, 0] was written with the global row number: the right image was read
        assert torch.equal(batch["x"][:, 0, 0, 0].long(), batch["index"])
        assert batch["x"].shape[1:] == (1, 8, 8)
        out.append(batch["index"])
    return torch.cat(out).numpy()


@pytest.mark.parametrize("window", [1, 3])
def test_each_image_once_per_epoch_any_workers(shards, window):
    paths, n = shards
    ds = ShardBatches(paths, 8, None, shuffle=True, seed=7, block_size=5, window=window)
    ds.set_epoch(0)
    serial = _epoch_indices(ds, 0)
    parallel = _epoch_indices(ds, 2)
    assert sorted(serial.tolist()) == list(range(n))
    np.testing.assert_array_equal(serial, parallel)  # order independent of workers
    assert not np.array_equal(serial, np.arange(n))  # shuffled
    ds.set_epoch(1)
    epoch1 = _epoch_indices(ds, 0)
    assert sorted(epoch1.tolist()) == list(range(n))
    assert not np.array_equal(epoch1, serial)  # differs between epochs
    again = ShardBatches(paths, 8, None, shuffle=True, seed=7, block_size=5, window=window)
    again.set_epoch(1)
    np.testing.assert_array_equal(
        _epoch_indices(again, 0), epoch1
    )  # reproducible per (seed, epoch)
    again.set_epoch(1)
    np.testing.assert_array_equal(
        _epoch_indices(again, 2, start=4), epoch1[4 * 8 :]
    )  # resume mid-epoch
    other = ShardBatches(paths, 8, None, shuffle=True, seed=8, block_size=5, window=window)
    assert not np.array_equal(_epoch_indices(other, 0), serial)


def test_blocks_are_contiguous_and_drop_last(shards):
    paths, n = shards
    ds = ShardBatches(paths, 10, None, block_size=5, drop_last=True)
    assert len(ds) == n // 10
    idx = _epoch_indices(ds, 0)
    assert len(idx) == 10 * (n // 10) and len(set(idx.tolist())) == len(idx)
    # window 1: rows come in runs of consecutive rows (blocks)
    assert (np.diff(idx) == 1).mean() > 0.5


def test_unshuffled_order_and_preprocessing(shards):
    paths, n = shards
    ds = ShardBatches(paths, 16, (5.0, 2.0), shuffle=False)
    batch = ds[1]
    np.testing.assert_array_equal(batch["index"].numpy(), np.arange(16, 32))
    with h5py.File(paths[0], "r") as fh:  # rows 16..31 of shard 0 (37 rows)
        raw = fh["images"][16:32]
        te, lx, ly = (fh[f"params/{k}"][16:32] for k in ("theta_e", "lens_x", "lens_y"))
        np.testing.assert_allclose(batch["gamma"].numpy(), fh["params/gamma_sub"][16:32], rtol=1e-6)
    ref = preprocess(raw, te, lx, ly, 5.0, 2.0)
    np.testing.assert_allclose(batch["x"][:, 0].numpy(), ref, atol=1e-6)
    assert len(ds[len(ds) - 1]["index"]) == n - 16 * (len(ds) - 1)
    np.testing.assert_allclose(read_labels(paths)[16:32], batch["gamma"].numpy(), rtol=1e-6)


def test_handles_not_shared_and_pickle(shards):
    paths, _ = shards
    ds = ShardBatches(paths, 8, None)
    ds[0]
    assert ds._files  # opened lazily in this process
    clone = pickle.loads(pickle.dumps(ds))
    assert clone._files == {}
    torch.testing.assert_close(clone[0], ds[0])
    ds.close()


def test_incomplete_shard_rejected(tmp_path):
    p = write_shard(tmp_path / "bad.h5", 5, 0, hw=4, complete=False)
    with pytest.raises(ValueError, match="complete"):
        ShardBatches([p], 2)


def test_unlabelled_shards(tmp_path):
    p = write_shard(tmp_path / "nfw.h5", 6, 0, hw=4)
    with h5py.File(p, "a") as fh:
        del fh["params/gamma_sub"]
    with pytest.raises(ValueError, match="gamma_sub"):
        ShardBatches([p], 3)
    batch = ShardBatches([p], 3, (0.0, 1.0), require_label=False, shuffle=False)[0]
    assert torch.isnan(batch["gamma"]).all() and torch.isfinite(batch["x"]).all()


def test_reads_shards_written_by_subslope_shards(tmp_path, rng):
    shards = pytest.importorskip("subslope.io.shards")
    n = 7
    images = rng.normal(size=(n, 10, 10)).astype(np.float32)
    params = {
        "theta_e": rng.uniform(0.9, 1.3, n),
        "lens_x": np.zeros(n),
        "lens_y": np.zeros(n),
        "set_index": np.arange(n),
        "noise_seed": np.arange(n, dtype=np.uint64),
        "gamma_sub": rng.uniform(1.1, 2.9, n),
    }
    path = shards.write_shard(
        tmp_path / "s.h5",
        images=images,
        params=params,
        psf=np.ones((3, 3)) / 9,
        subhalos={"counts": np.zeros(n, dtype=np.int64)},
        los={"counts": np.zeros(n, dtype=np.int64)},
        attrs={"seed": 1},
    )
    batch = ShardBatches([path], 4, (0.0, 2.0), shuffle=False)[1]
    ref = preprocess(images[4:], params["theta_e"][4:], 0.0, 0.0, 0.0, 2.0)
    np.testing.assert_allclose(batch["x"][:, 0].numpy(), ref, atol=1e-6)
    np.testing.assert_allclose(batch["gamma"].numpy(), params["gamma_sub"][4:], rtol=1e-6)
