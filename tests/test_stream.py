"""Training on a live simulator stream (training.data: stream): batches as a pure function
of (seed, epoch, batch), the same for any number of workers, resumable, the real scene
simulator, and the campaign's plan without training shards."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from test_nre_data import write_shard

from subslope import config as cfgmod
from subslope import plan
from subslope.nre.data import make_loader
from subslope.nre.stream import StreamBatches
from subslope.nre.train import train
from subslope.stages.simulate import runnable_config
from subslope.stages.train import training_section, training_stream
from tests.conftest import REPO_ROOT, run_snakemake

HW = 32


class ToySimulator:
    """Images whose brightness grows with γ, plus noise: learnable in a few steps."""

    def images(self, n, seed_sequence):
        rng = np.random.default_rng(seed_sequence)
        gamma = rng.uniform(1.1, 2.9, n)
        images = 11.0 + 3.0 * (gamma[:, None, None] - 2.0) + rng.normal(0, 3.0, (n, HW, HW))
        params = {
            "gamma_sub": gamma,
            "theta_e": np.full(n, 0.6),
            "lens_x": np.zeros(n),
            "lens_y": np.zeros(n),
        }
        return images.astype(np.float32), params

    def labels(self, n, seed_sequence):
        return np.random.default_rng(seed_sequence).uniform(1.1, 2.9, n)


def _stream(**kw):
    return StreamBatches(ToySimulator(), 16, 4, (11.0, 3.0), seed=3, **kw)


def test_batches_are_a_function_of_seed_epoch_and_batch():
    ds = _stream()
    first = ds[1]
    assert first["x"].shape == (16, 1, HW, HW) and torch.all(torch.isfinite(first["x"]))
    torch.testing.assert_close(_stream()[1]["x"], first["x"], rtol=0, atol=0)
    assert not torch.equal(ds[0]["x"], first["x"])
    ds.set_epoch(1)
    assert not torch.equal(ds[1]["x"], first["x"])  # every epoch sees new images
    np.testing.assert_array_equal(ds[1]["index"].numpy(), 16 + np.arange(16))
    with pytest.raises(IndexError, match="out of range"):
        ds[4]
    labels = ds.labels(5000)
    assert labels.shape == (5000,) and 1.1 <= labels.min() and labels.max() <= 2.9
    with pytest.raises(ValueError, match="n_batches"):
        StreamBatches(ToySimulator(), 16, 0)


@pytest.mark.parametrize("workers", [1, 2])
def test_workers_give_the_same_stream(workers):
    ds = _stream()
    ds.set_epoch(2)
    alone = [b["x"] for b in make_loader(ds, start=1)]
    pooled = [b["x"] for b in make_loader(ds, start=1, num_workers=workers)]
    assert len(alone) == len(pooled) == 3
    for a, b in zip(alone, pooled):
        assert torch.equal(a, b)


def test_training_on_a_stream_resumes_exactly(tmp_path):
    val = [write_shard(tmp_path / "v0.h5", 24, 2, hw=HW, signal=3.0)]
    cfg = {
        "arch": {"depth": 10, "width": 0.0625, "head": [16]},
        "batch_size": 16,
        "max_epochs": 2,
        "deterministic": True,
        "progress": False,
        "checkpoint_every": 2,
        "seed": 3,
        "data": "stream",
    }
    full = train(cfg, _stream(), val, (11.0, 3.0), tmp_path / "a", tmp_path / "a_ck", device="cpu")
    assert full["finished"] and full["epochs"] == 2
    part = train(
        dict(cfg, max_steps=5), _stream(), val, (11.0, 3.0), tmp_path / "b", tmp_path / "b_ck"
    )
    assert not part["finished"] and part["step"] == 5
    resumed = train(
        dict(cfg, num_workers=2), _stream(), val, (11.0, 3.0), tmp_path / "b", tmp_path / "b_ck"
    )
    assert resumed["finished"]
    a = torch.load(tmp_path / "a" / "model.pt", weights_only=False)["model"]
    b = torch.load(tmp_path / "b" / "model.pt", weights_only=False)["model"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(ValueError, match="batches of 16 images, training.batch_size is 8"):
        train(dict(cfg, batch_size=8), _stream(), val, (11.0, 3.0), tmp_path / "c", tmp_path / "c")


@pytest.fixture(scope="module")
def stream_config():
    from tests.conftest import shared_data_dir

    data = shared_data_dir()
    if not (data / "cosmos").is_dir():
        pytest.skip(f"no data mirror at {data}")
    over = {
        "data": {"resources_dir": str(data)},
        "training": {"data": "stream"},
        "domain": {"scene": "validation"},
        "simulation": {"scenes": {"train": {"n_shards": 2, "images_per_shard": 4}}},
    }
    return cfgmod.load(REPO_ROOT / "config" / "tiny.yaml", overrides=over, env=False)


def test_scene_stream_simulates_the_train_scene(stream_config):
    """The real simulator in two forked workers gives the batches of the training
    process, each the images simulate_images makes from the batch's seeds."""
    from subslope.simulation.shard import simulate_images

    job = runnable_config(plan.shard_job_config(stream_config, "train"), stream_config)
    ds = training_stream(training_section(stream_config), job)
    assert len(ds) == 2 and ds.batch_size == 4  # 2 x 4 images an epoch, batches of 4
    alone = [b for b in make_loader(ds)]
    pooled = [b for b in make_loader(ds, num_workers=2)]
    for a, b in zip(alone, pooled, strict=True):
        assert torch.equal(a["x"], b["x"]) and torch.equal(a["gamma"], b["gamma"])
    direct = simulate_images(job, "train", 4, ds.seed_sequence(1))
    np.testing.assert_array_equal(alone[1]["x"][:, 0].numpy(), direct["images"])  # no whitening
    assert torch.equal(alone[1]["gamma"], torch.from_numpy(direct["params"]["gamma_sub"]).float())
    labels = ds.labels(2000)
    assert 1.1 <= labels.min() and labels.max() <= 2.9


def test_a_streamed_campaign_plans_no_training_shards(stream_config, workdir, data_dir):
    jobs = plan.shard_jobs(stream_config)
    simulated = {s for s, c in stream_config["simulation"]["scenes"].items() if c["n_shards"]}
    assert {j["scene"] for j in jobs} == simulated - {"train"}
    bad = copy.deepcopy(stream_config)
    bad["domain"]["scene"] = "train"
    with pytest.raises(cfgmod.ConfigError, match="domain.scene = 'train'.*training.data = stream"):
        cfgmod.validate(bad)
    bad = copy.deepcopy(stream_config)
    bad["simulation"]["scenes"]["validation"]["n_shards"] = 0
    bad["simulation"]["scenes"]["train"]["images_per_shard"] = 1
    bad["calibration"]["single_scene"] = "test_epl"
    with pytest.raises(cfgmod.ConfigError, match=r"2 images, fewer than one batch(.|\n)*needs val"):
        cfgmod.validate(bad)
    overlay = workdir / "config" / "tiny_stream.yaml"
    overlay.write_text("base: tiny.yaml\ntraining: {data: stream}\ndomain: {scene: validation}\n")
    proc = run_snakemake(workdir, "-n", "--configfile", str(overlay), mirror=data_dir)
    overlay.unlink()
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "results/simulate_shard/train/" not in proc.stdout
    assert "train_estimator" in proc.stdout and "compute_whitening" in proc.stdout


def test_cli_train_takes_no_shards_with_a_stream(tmp_path, capsys):
    from subslope.cli import main

    cfg = tmp_path / "stream.yaml"
    cfg.write_text(
        f"base: {REPO_ROOT / 'config' / 'tiny.yaml'}\n"
        "training: {data: stream}\ndomain: {scene: validation}\n"
    )
    common = ["--val", "v.h5", "--whitening", "w.json", "--out", str(tmp_path / "o")]
    assert main(["train", "--config", str(cfg), "--train", "t.h5", *common]) == 1
    assert "training.data is 'stream'" in capsys.readouterr().err
    assert main(["train", "--config", str(REPO_ROOT / "config" / "tiny.yaml"), *common]) == 1
    assert "--train: give the training shard files" in capsys.readouterr().err
