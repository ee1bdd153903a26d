"""Training loop: artifact, early stopping, checkpoint/resume reproducibility."""

from __future__ import annotations

import csv
import functools
import math

import pytest
import torch
from test_nre_data import write_shard

from subslope.nre.train import load_estimator, resolve_config, train

TINY = {"depth": 10, "width": 0.0625, "head": [16]}


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    d = tmp_path_factory.mktemp("nre_shards")
    train_paths = [
        write_shard(d / "t0.h5", 45, 0, hw=32, signal=3.0),
        write_shard(d / "t1.h5", 38, 1, hw=32, signal=3.0, offset=45),
    ]
    val_paths = [write_shard(d / "v0.h5", 24, 2, hw=32, signal=3.0)]
    return train_paths, val_paths


def _config_of(**kw):
    cfg = {
        "arch": TINY,
        "batch_size": 16,
        "max_epochs": 3,
        "deterministic": True,
        "progress": False,
        "negatives": "derangement",
        "checkpoint_every": 2,
        "block_size": 8,
        "seed": 3,
    }
    cfg.update(kw)
    return cfg


WHITENING = (11.0, 3.0)
_config = _config_of


@pytest.mark.parametrize("augment", ["none", "dihedral"])
def test_resume_reproduces_uninterrupted_run(shards, tmp_path, augment):
    tr, va = shards
    _config = functools.partial(_config_of, augment=augment)
    full = train(_config(), tr, va, WHITENING, tmp_path / "a_out", tmp_path / "a_ck", device="cpu")
    assert full["finished"] and full["epochs"] == 3

    out, ck = tmp_path / "b_out", tmp_path / "b_ck"
    part = train(
        _config(max_steps=3), tr, va, WHITENING, out, ck, device="cpu"
    )  # mid epoch 0 (5 batches/epoch)
    assert not part["finished"] and part["step"] == 3 and part["model"] is None
    assert not (out / "model.pt").exists() and (ck / "last.pt").exists()
    part = train(_config(max_steps=7), tr, va, WHITENING, out, ck, device="cpu")  # mid epoch 1
    assert part["step"] == 7 and part["epochs"] == 1
    resumed = train(_config(num_workers=2), tr, va, WHITENING, out, ck, device="cpu")
    assert resumed["finished"] and resumed["step"] == full["step"] == 15

    a, meta_a = load_estimator(full["model"])
    b, meta_b = load_estimator(resumed["model"])
    for (name, pa), pb in zip(a.state_dict().items(), b.state_dict().values()):
        assert torch.equal(pa, pb), f"{name} differs after resume"
    assert [r["val_loss"] for r in meta_a["history"]] == [r["val_loss"] for r in meta_b["history"]]
    assert [r["train_loss"] for r in meta_a["history"]] == pytest.approx(
        [r["train_loss"] for r in meta_b["history"]], abs=1e-12
    )

    # a finished run called again just rewrites the artifact
    again = train(_config(), tr, va, WHITENING, out, ck, device="cpu")
    assert again["finished"] and again["step"] == 15
    with pytest.raises(ValueError, match="lr"):
        train(_config(lr=1e-2), tr, va, WHITENING, out, ck, device="cpu")


def test_artifact_learning_and_log(shards, tmp_path):
    tr, va = shards
    res = train(
        _config(
            max_epochs=8,
            batch_size=8,
            negatives="roll",
            deterministic=False,
            arch={**TINY, "head": [32, 32]},
            lr=3e-3,
        ),
        tr,
        va,
        {"mean": 11.0, "std": 3.0},
        tmp_path / "out",
        tmp_path / "ck",
    )
    model, meta = load_estimator(res["model"])
    assert not model.training
    assert meta["whitening"] == {"mean": 11.0, "std": 3.0}
    assert meta["model_card"]["arch"]["depth"] == 10 and meta["model_card"]["n_params"] > 0
    assert meta["gamma_norm"]["mean"] == pytest.approx(2.0, abs=0.2)
    assert meta["config"] == resolve_config(meta["config"]) and len(meta["config_hash"]) == 16
    assert meta["preprocess"] == {"pixel_scale": 0.04, "mask_factor": 1.5}
    rows = list(csv.DictReader(open(tmp_path / "out" / "training_log.csv")))
    assert [int(r["epoch"]) for r in rows] == list(range(8))
    assert set(rows[0]) == {"epoch", "train_loss", "val_loss", "lr", "seconds", "images_per_s"}
    assert all(float(r["images_per_s"]) > 0 for r in rows)
    # the image mean carries γ: the classifier must clearly beat chance (ln 2 = 0.693;
    # a network that ignores the image, or labels misaligned with images, stay at ~0.69)
    assert meta["best_val_loss"] < 0.67, [r["val_loss"] for r in rows]
    assert meta["best_val_loss"] == pytest.approx(min(float(r["val_loss"]) for r in rows))


def test_early_stopping_and_lr_schedule(shards, tmp_path):
    tr, va = shards
    # min_delta so large that no epoch counts as an improvement after the first
    res = train(
        _config(
            max_epochs=10,
            min_delta=10.0,
            early_stop_patience=2,
            lr_patience=0,
            lr_cooldown=0,
            deterministic=False,
        ),
        tr,
        va,
        WHITENING,
        tmp_path / "o",
        tmp_path / "c",
    )
    assert res["stop_reason"] == "early_stop" and res["epochs"] == 3
    _, meta = load_estimator(res["model"])
    lrs = [r["lr"] for r in meta["history"]]
    assert lrs[0] == pytest.approx(1e-3) and lrs[-1] < lrs[0]  # plateau → ×0.1


def test_bad_config():
    with pytest.raises(ValueError, match="unknown"):
        resolve_config({"learning_rate": 1e-3})
    with pytest.raises(ValueError, match="batch_size"):
        resolve_config({"batch_size": 1})
    with pytest.raises(ValueError, match="amp"):
        resolve_config({"amp": "fp8"})
    assert math.isclose(resolve_config({})["lr"], 1e-3)


@pytest.mark.gpu
def test_cuda_mixed_precision(shards, tmp_path):
    tr, va = shards
    res = train(
        _config(max_epochs=2, amp="auto"), tr, va, WHITENING, tmp_path / "o", tmp_path / "c"
    )  # device picked: cuda
    assert res["finished"]
    model, meta = load_estimator(res["model"])  # CPU tensors whatever the training device
    assert all(p.device.type == "cpu" for p in model.parameters())
    assert all(math.isfinite(r["val_loss"]) for r in meta["history"])
