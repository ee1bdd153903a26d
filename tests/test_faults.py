"""Fault injection: bad configs, corrupt and truncated files, killed writers, a full disk,
changed inputs and failed reruns. Each test asserts the message (the key or file named,
what is wrong, how to recover) and that nothing good is lost."""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
import yaml

from subslope.io import atomic
from subslope.io import resources as res
from subslope.io.shards import ShardError, file_sha256, open_shard, write_shard
from tests.conftest import REPO_ROOT, TINY, run_snakemake

TINY_YAML = REPO_ROOT / "config" / "tiny.yaml"
NO_CUDA = pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")

# ---------------------------------------------------------------------------------------
# Configs: every problem seen before the first job, naming the key and what is allowed.

#: (keys merged over config/tiny.yaml, or a raw file text; what the error must say)
BAD_CONFIGS = [
    ({"seed": -1}, r"seed = -1 is not allowed"),
    ({"run_name": 5}, r"run_name = 5 is not allowed"),
    ({"simulaton": {}}, r"unknown config key\(s\) simulaton"),
    ({"simulation": {"scenes": {"train": {"n_shards": -1}}}}, r"simulation.scenes.train.n_shards"),
    ({"simulation": {"render": {"device": "tpu"}}}, r"simulation.render.device = 'tpu'"),
    ({"simulation": {"render": {"dtype": "float16"}}}, r"simulation.render.dtype"),
    (
        {"simulation": {"scenes": {"test_epl": {"images_per_shard": 3}}}},
        r"simulation.scenes.test_epl.images_per_shard = 3 must be a multiple",
    ),
    (
        {"simulation": {"sources": {"split": {"train": 0.8, "validation": 0.1, "test": 0.05}}}},
        r"simulation.sources.split.train/validation/test = 0.8/0.1/0.05 must sum to 1",
    ),
    (
        {"simulation": {"sources": {"folder": ["cosmos", "nowhere"]}}},
        r"simulation.sources.folder: \['nowhere'\] neither a registered data folder",
    ),
    (
        {"scenes": {"train": {"main_lens": {"gamma": {"dist": "fixed", "value": 3.0}}}}},
        r"scenes.train.main_lens.gamma",
    ),
    (
        {"scenes": {"nfw": {"main_lens": {"gamma": {"dist": "uniform", "low": 1.0, "high": 2}}}}},
        r"scenes.nfw.main_lens.gamma",
    ),
    ({"scenes": {"train": {"subhalos": {"count": {"dist": "gauss"}}}}}, r"scenes.train"),
    ({"instrument": {"pixel_scale": -0.04}}, r"instrument.pixel_scale = -0.04"),
    ({"training": {"batch_size": 0}}, r"training.batch_size = 0"),
    ({"training": {"device": "tpu"}}, r"training.device = 'tpu'"),
    ({"inference": {"gamma_grid": {"n": 2}}}, r"inference.gamma_grid.n = 2"),
    ({"calibration": {"level": 1.5}}, r"calibration.level = 1.5"),
    (
        {"instrument": {"psf": {"file": "psf/none.fits"}}},
        r"instrument.psf.file = 'psf/none.fits': neither a registered data file",
    ),
    ({"hst": {"combine": ["SDSSJ0000+0000"]}}, r"hst.combine: unknown system\(s\)"),
    ({"hst": {"highlight": ["J0946"]}}, r"hst.highlight: unknown system\(s\) \['J0946'\]"),
    ({"domain": {"bounds": [99.0, 1.0]}}, r"domain.bounds = \[99.0, 1.0\]: need low < high"),
    ({"stages": {"train": "yes"}}, r"stages.train = 'yes'"),
    ({"data": {"resources_dir": 5}}, r"data.resources_dir = 5"),
    ({"base": "missing.yaml"}, r"config key base = 'missing.yaml' in .*: no such file"),
    ("seed: [1, 2\n", r"is not valid YAML"),
    ("- 1\n- 2\n", r"must hold a mapping of keys, not list"),
]
NO_CUDA_CONFIGS = [
    ({"training": {"device": "cuda"}}, r"training.device = 'cuda': this machine has no CUDA"),
    ({"inference": {"device": "cuda"}}, r"inference.device = 'cuda': this machine has no CUDA"),
]


def _bad_file(tmp_path: Path, override, data_dir: Path) -> Path:
    """A config file on tiny.yaml (its `base`) with ``override`` on top, in ``tmp_path``."""
    path = tmp_path / "bad.yaml"
    if isinstance(override, str):
        path.write_text(override)
        return path
    keys = {"base": str(TINY_YAML), "data": {"resources_dir": str(data_dir)}}
    for key, value in override.items():
        keys[key] = {**keys[key], **value} if key == "data" else value
    if override.get("base"):
        keys["base"] = override["base"]
    path.write_text(yaml.safe_dump(keys))
    return path


def test_there_are_enough_bad_configs():
    assert len(BAD_CONFIGS) + len(NO_CUDA_CONFIGS) >= 20


@pytest.mark.parametrize(
    ("override", "match"),
    BAD_CONFIGS + [pytest.param(*c, marks=NO_CUDA) for c in NO_CUDA_CONFIGS],
    ids=lambda v: (
        re.sub(r"\W+", "_", str(v))[:40] if not isinstance(v, str) or "\\" not in v else ""
    ),
)
def test_validate_config_names_the_key(tmp_path, data_dir, capsys, override, match):
    from subslope.cli import main

    path = _bad_file(tmp_path, override, data_dir)
    assert main(["validate-config", "-q", str(path)]) == 1
    err = capsys.readouterr().err
    assert re.search(match, err), err


#: Bad configs also run through `snakemake -n`: the workflow refuses them when it loads
#: with the same message (one file read and checked one way).
WORKFLOW_CASES = [BAD_CONFIGS[i] for i in (0, 6, 7, 8, 9, 17, 18)]


@pytest.mark.slow
@pytest.mark.parametrize(("override", "match"), WORKFLOW_CASES)
def test_the_workflow_refuses_what_validate_config_refuses(
    workdir, tmp_path, data_dir, override, match
):
    path = _bad_file(tmp_path, override, data_dir)
    proc = run_snakemake(workdir, "-n", "--configfile", str(path), mirror=data_dir)
    assert proc.returncode != 0
    assert re.search(match, proc.stdout + proc.stderr), proc.stdout + proc.stderr


@NO_CUDA
@pytest.mark.slow
def test_cuda_without_cuda_stops_a_local_run_before_any_job(tmp_path, data_dir):
    from tests.conftest import workflow_copy

    root = workflow_copy(tmp_path)
    proc = run_snakemake(
        root, "--cores", "1", *TINY, "--config", 'training={"device": "cuda"}', mirror=data_dir
    )
    assert proc.returncode != 0
    out = proc.stdout + proc.stderr
    assert "config key training.device = 'cuda': this machine has no CUDA device" in out, out
    assert not (root / "results").exists() and not (root / "resources").exists()


def test_cli_and_workflow_read_a_file_the_same_way(tmp_path):
    """tiny.yaml sits on config.yaml (`base`), for the CLI as for the workflow; keys a file
    leaves out take its base's values, not the schema defaults."""
    from subslope import config as cfg

    tiny = cfg.load(TINY_YAML, env=False)
    base = cfg.load(REPO_ROOT / "config" / "config.yaml", env=False)
    assert (
        tiny["simulation"]["sources"]["mag_renormalize"]
        == (base["simulation"]["sources"]["mag_renormalize"])
    )
    assert tiny["simulation"]["sources"]["mag_renormalize"] != cfg.validate({})["simulation"][
        "sources"
    ].get("mag_renormalize")
    (tmp_path / "a.yaml").write_text("base: b.yaml\nseed: 1\n")
    (tmp_path / "b.yaml").write_text("base: a.yaml\nseed: 2\n")
    with pytest.raises(cfg.ConfigError, match=r"base of .*a.yaml makes a cycle"):
        cfg.load(tmp_path / "a.yaml")


@pytest.mark.slow
def test_the_cli_writes_the_shard_the_workflow_wrote(tiny_run, tmp_path, data_dir):
    """`subslope simulate --config config/tiny.yaml` gives the workflow's shard: every
    dataset bit for bit and every attribute but `cosmos_folder`, where this machine keeps
    the data. One config file, one campaign."""
    from subslope.cli import main

    config = tmp_path / "tiny.yaml"
    config.write_text(
        yaml.safe_dump(
            {
                "base": str(TINY_YAML),
                "data": {"resources_dir": str(data_dir)},
                "simulation": {"shard_cache": str(tmp_path / "cache")},
            }
        )
    )
    out = tmp_path / "shard_0.h5"
    args = ["simulate", "--config", str(config), "--scene", "validation", "--shard", "0"]
    assert main([*args, "--out", str(out), "--quiet"]) == 0
    workflow_shard = tiny_run / "simulate_shard" / "validation" / "shard_0.h5"
    with h5py.File(out) as mine, h5py.File(workflow_shard) as theirs:
        assert set(mine.attrs) == set(theirs.attrs)
        for key in set(mine.attrs) - {"cosmos_folder"}:
            assert str(mine.attrs[key]) == str(theirs.attrs[key]), key
        names: list[str] = []
        theirs.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) else None)
        assert "images" in names
        for name in names:
            assert np.array_equal(mine[name][()], theirs[name][()]), name


# ---------------------------------------------------------------------------------------
# Shards: truncated, corrupt chunk, flipped label, old format, killed writer.


def _shard(path: Path, n: int = 6, overwrite: bool = False) -> Path:
    rng = np.random.default_rng(0)
    return write_shard(
        path,
        images=rng.random((n, 16, 16)).astype(np.float32),
        params={
            "gamma_sub": rng.uniform(1.1, 2.9, n),
            "theta_e": np.full(n, 1.2),
            "lens_x": np.zeros(n),
            "lens_y": np.zeros(n),
            "set_index": np.arange(n),
            "noise_seed": np.arange(n, dtype=np.uint64),
        },
        psf=np.ones((3, 3)) / 9,
        subhalos={"counts": np.zeros(n, np.int64)},
        los={"counts": np.zeros(n, np.int64)},
        attrs={"scene": "train"},
        overwrite=overwrite,
    )


def _flip_chunk(path: Path, dataset: str, index: int = 0) -> None:
    with h5py.File(path, "r") as fh:
        info = fh[dataset].id.get_chunk_info(index)
        offset, size = info.byte_offset, info.size
    data = bytearray(path.read_bytes())
    data[offset + size // 2] ^= 0xFF
    path.write_bytes(bytes(data))


def test_truncated_shard_names_the_file_and_the_way_back(tmp_path):
    path = _shard(tmp_path / "shard_0.h5")
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(ShardError, match=r"shard_0.h5 is not a readable HDF5 file \(truncated"):
        open_shard(path)
    with pytest.raises(ShardError, match=r"delete .*shard_0.h5 and run snakemake again"):
        open_shard(path)
    from subslope.nre.data import shard_lengths

    with pytest.raises(ShardError, match=r"shard_0.h5 is not a readable HDF5 file"):
        shard_lengths([path])


def test_broken_result_json_names_the_file(tmp_path):
    from subslope.io.atomic import ResultFileError
    from subslope.nre.preprocess import read_whitening
    from subslope.stages.calibrate import load_thresholds

    path = tmp_path / "thresholds.json"
    path.write_text('{"tau": {"1": 2.')
    with pytest.raises(ResultFileError, match=r"thresholds.json is not valid JSON .* delete it"):
        load_thresholds(path)
    with pytest.raises(ResultFileError, match=r"thresholds.json is not valid JSON"):
        read_whitening(path)


def test_corrupt_image_chunk_names_the_image(tmp_path):
    from subslope.nre.data import ShardBatches
    from subslope.nre.whitening import pixel_statistics

    path = _shard(tmp_path / "shard_0.h5")
    _flip_chunk(path, "images", 3)
    with open_shard(path) as shard:  # the last image is fine
        assert shard.images[5].shape == (16, 16)
        with pytest.raises(ShardError, match=r"shard_0.h5: images image 3 cannot be read"):
            shard.images[0:6]
    with pytest.raises(ShardError, match=r"images image 3 .* the file is corrupt; delete"):
        pixel_statistics([path])
    from subslope.io.shards import verify_shard

    with pytest.raises(ShardError, match=r"images image 3 cannot be read"):
        verify_shard(path)
    assert verify_shard(_shard(tmp_path / "good.h5")) == 6
    batches = ShardBatches([path], batch_size=6, shuffle=False)
    with pytest.raises(ShardError, match=r"shard_0.h5: images image 3 cannot be read"):
        batches[0]


def test_flipped_label_is_refused_when_read(tmp_path):
    from subslope.nre.data import read_labels

    path = _shard(tmp_path / "shard_0.h5")
    _flip_chunk(path, "params/gamma_sub")
    with pytest.raises(ShardError, match=r"shard_0.h5: params/gamma_sub row 0 cannot be read"):
        read_labels([path])
    with pytest.raises(ShardError, match=r"params/gamma_sub"), open_shard(path) as shard:
        assert shard.params


def test_shard_of_an_older_format_is_refused(tmp_path):
    path = _shard(tmp_path / "shard_0.h5")
    with h5py.File(path, "r+") as fh:
        fh.attrs["format_version"] = 1
    with pytest.raises(ShardError, match=r"format version 1; this subslope reads version 3"):
        open_shard(path)


KILLED_WRITER = """
import sys, time, numpy as np
from subslope.io import atomic
with atomic.atomic_write(sys.argv[1]) as tmp:
    tmp.write_bytes(b"partial")
    print(tmp, flush=True)
    time.sleep(60)
"""


def test_killed_shard_writer_leaves_nothing_at_the_path(tmp_path):
    """SIGKILL mid-shard: no file at the shard's path; its temporary is removed by the next
    write, which gives the same bytes as an uninterrupted one."""
    path = tmp_path / "shard_0.h5"
    proc = subprocess.Popen(
        [sys.executable, "-c", KILLED_WRITER, str(path)], stdout=subprocess.PIPE, text=True
    )
    tmp = Path(proc.stdout.readline().strip())
    assert tmp.is_file() and tmp.parent == tmp_path
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not path.exists() and tmp.exists()
    _shard(path)
    assert not tmp.exists() and [p.name for p in tmp_path.iterdir()] == ["shard_0.h5"]
    assert file_sha256(path) == file_sha256(_shard(tmp_path / "again.h5"))


# ---------------------------------------------------------------------------------------
# Checkpoints and estimator files.


def test_truncated_checkpoint_and_model_name_the_file(tmp_path):
    from subslope.nre.checkpoints import CheckpointError, atomic_save, torch_load
    from subslope.nre.train import load_estimator

    for name in ("last.pt", "model.pt"):
        path = tmp_path / name
        atomic_save({"format": "subslope.nre/1", "x": torch.arange(10_000.0)}, path)
        path.write_bytes(path.read_bytes()[:1000])
        with pytest.raises(CheckpointError, match=rf"{name} \(1000 bytes\) cannot be read: trunc"):
            torch_load(path, "cpu", "delete it")
    with pytest.raises(CheckpointError, match=r"model.pt .* delete it and run snakemake again"):
        load_estimator(tmp_path / "model.pt")


@pytest.mark.slow
def test_training_killed_mid_epoch_resumes_to_the_same_model(tiny_run, tmp_path):
    """SIGKILL of `subslope train` in the epoch after its first checkpoint; the rerun
    resumes and ends with the weights of an uninterrupted run, tensor for tensor."""
    config = tmp_path / "train.yaml"
    config.write_text(
        yaml.safe_dump(
            {
                "base": str(TINY_YAML),
                "training": {"max_epochs": 25, "early_stop_patience": 100},
            }
        )
    )
    shards = tiny_run / "simulate_shard"
    args = [
        sys.executable, "-m", "subslope.cli", "train", "--config", str(config),
        "--train", *map(str, sorted((shards / "train").glob("shard_*.h5"))),
        "--val", str(shards / "validation" / "shard_0.h5"),
        "--whitening", str(tiny_run / "compute_whitening" / "whitening.json"),
    ]  # fmt: skip
    env = dict(os.environ, OMP_NUM_THREADS="1")
    whole = tmp_path / "whole"
    subprocess.run([*args, "--out", str(whole)], check=True, env=env, capture_output=True)
    killed = tmp_path / "killed"
    proc = subprocess.Popen([*args, "--out", str(killed)], env=env, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while not list(killed.rglob("last.pt")) and time.monotonic() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    (last,) = killed.rglob("last.pt")
    assert torch.load(last, weights_only=True)["state"]["epoch"] < 24  # killed mid-run
    assert not (killed / "model.pt").exists()
    subprocess.run([*args, "--out", str(killed)], check=True, env=env, capture_output=True)
    a = torch.load(whole / "model.pt", weights_only=True)["model"]
    b = torch.load(killed / "model.pt", weights_only=True)["model"]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_checkpoints_follow_the_content_of_the_shards(tmp_path):
    """A shard rewritten under the same path (a simulator fix, a new PSF) gets a new
    checkpoint folder, so training never resumes on other images; a whitening file
    computed from other contents is refused, naming it."""
    from subslope.stages.train import data_fingerprint

    train, val = _shard(tmp_path / "train_0.h5"), _shard(tmp_path / "val_0.h5", n=4)
    white = tmp_path / "whitening.json"

    def whitening_of(path):
        shards = [{"path": str(path), "sha256": file_sha256(path)}]
        white.write_text(json.dumps({"mean": 0.0, "std": 1.0, "shards": shards}))

    whitening_of(train)
    first = data_fingerprint([train], [val], white)
    assert first == data_fingerprint([train], [val], white)
    _shard(train, n=5, overwrite=True)  # other images under the same path
    with pytest.raises(ValueError, match=r"whitening.json was computed from other contents"):
        data_fingerprint([train], [val], white)
    whitening_of(train)
    assert data_fingerprint([train], [val], white) != first
    _shard(val, n=3, overwrite=True)
    assert len({first, data_fingerprint([train], [val], white)}) == 2


# ---------------------------------------------------------------------------------------
# A full disk.


def test_disk_full_is_named_and_leaves_nothing(tmp_path, monkeypatch):
    """ENOSPC injected into a shard write and a checkpoint write: a DiskFullError naming the
    file and its file system; the previous file and no temporary remain."""
    from subslope.nre.checkpoints import atomic_save

    good = _shard(tmp_path / "shard_0.h5")
    before = good.read_bytes()

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(h5py.Dataset, "__setitem__", full)
    monkeypatch.setattr(h5py.Group, "create_dataset", full)
    with pytest.raises(atomic.DiskFullError, match=r"no space left to write .*shard_0.h5: the"):
        _shard(good, overwrite=True)
    assert good.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["shard_0.h5"]
    monkeypatch.undo()

    def short_write(obj, f, *args, **kwargs):
        Path(f).write_bytes(b"PK partial")
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 576 vs 534")

    monkeypatch.setattr(torch, "save", short_write)
    monkeypatch.setattr(atomic.shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(1, 1, 0))
    with pytest.raises(atomic.DiskFullError, match=r"last.pt: the file system mounted at"):
        atomic_save({"x": 1}, tmp_path / "last.pt")
    assert [p.name for p in tmp_path.iterdir()] == ["shard_0.h5"]


def _tmpfs(path: Path, size: str = "1m") -> bool:
    path.mkdir()
    ok = (
        os.geteuid() == 0
        and shutil.which("mount") is not None
        and subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
            capture_output=True,
        ).returncode
        == 0
    )
    return ok


FULL_DISK = """
import sys
from pathlib import Path
import torch
from subslope.io.atomic import DiskFullError
from subslope.nre.checkpoints import atomic_save
from tests.test_faults import _shard

disk = Path(sys.argv[1])
for what, write in (
    ("checkpoint", lambda: atomic_save({"x": torch.zeros(1_000_000)}, disk / "last.pt")),
    ("shard", lambda: _shard(disk / "shard_0.h5", n=2_000)),
):
    try:
        write()
    except DiskFullError as exc:
        print(what, exc, flush=True)
"""


def test_disk_full_on_a_real_small_disk(tmp_path):
    """The same on a 1 MiB tmpfs (needs root and mount; skipped elsewhere). In a separate
    process, as a job meets it: HDF5 keeps the handles of a file it failed to close, so
    the process that met a full disk should end, as a job does."""
    disk = tmp_path / "disk"
    if not _tmpfs(disk):
        pytest.skip("cannot mount a tmpfs here (needs root)")
    try:
        proc = subprocess.run(
            [sys.executable, "-c", FULL_DISK, str(disk)],
            capture_output=True,
            text=True,
            cwd=REPO_ROOT,
            timeout=120,
        )
        lines = proc.stdout.splitlines()
        assert len(lines) == 2, proc.stdout + proc.stderr
        assert lines[0].startswith(f"checkpoint [Errno 28] no space left to write {disk}/last.pt")
        assert f"the file system mounted at {disk} has" in lines[0]
        assert lines[1].startswith(f"shard [Errno 28] no space left to write {disk}/shard_0.h5")
        assert list(disk.iterdir()) == []
    finally:
        subprocess.run(["umount", str(disk)], check=False)


# ---------------------------------------------------------------------------------------
# Resources.


def test_resource_changed_after_fetch_is_refused(tmp_path, data_dir):
    """A data file changed after fetch_data is refused by the job that reads it."""
    [psf] = res.fetch_files([tmp_path / "psf" / "emp_psf_f814w.fits"], mirror=data_dir)
    other = tmp_path / "shard_0.h5"
    other.write_bytes(b"not registered")
    assert res.verify_files([psf, other]) == 1
    raw = bytearray(psf.read_bytes())
    raw[5000:5016] = bytes(b ^ 0xFF for b in raw[5000:5016])
    psf.write_bytes(bytes(raw))
    with pytest.raises(
        res.ChecksumError,
        match=r"emp_psf_f814w.fits changed after .*delete it and run snakemake again",
    ):
        res.verify_files([psf])
    psf.unlink()
    with pytest.raises(res.MissingResourceError, match="is missing"):
        res.verify_files([psf])


# ---------------------------------------------------------------------------------------
# The workflow: one fetch job per file, failed reruns keep the previous results, umask.


@pytest.fixture
def finished_campaign(tiny_run, tmp_path):
    """A copy of the finished tiny campaign (time stamps and Snakemake's records kept)."""
    src = tiny_run.parent
    dst = tmp_path / "campaign"
    shutil.copytree(src, dst, symlinks=True, ignore=shutil.ignore_patterns(".*.tmp"))
    return dst


@pytest.mark.slow
def test_a_deleted_data_file_comes_back_and_nothing_reruns(finished_campaign, data_dir, tmp_path):
    root = finished_campaign
    resources = root / "resources"
    # the PSF every shard reads and one HST cutout: restored from the mirror before the
    # graph is built, with the time stamp and bytes they had, so no reader runs again
    for rel in ("psf/emp_psf_f814w.fits", "hst/SDSSJ0946+1006_npix100.npy"):
        target = resources / rel
        when = target.stat().st_mtime
        target.unlink()
        proc = run_snakemake(root, "-n", *TINY, mirror=data_dir)
        assert proc.returncode == 0, proc.stderr
        assert "Nothing to be done" in proc.stdout, proc.stdout
        assert f"{rel} was deleted; restored from the data mirror" in proc.stdout + proc.stderr
        assert target.stat().st_mtime == pytest.approx(when, abs=5)  # as first fetched
        assert res.sha256sum(target) == res.sha256sum(data_dir / rel)
    # the mirror unreachable: fetch_data fails on that one file, the others stay as they were
    target.unlink()
    before = {p: p.stat().st_mtime for p in resources.rglob("*") if p.is_file()}
    proc = run_snakemake(root, "--cores", "1", *TINY, mirror=tmp_path / "unreachable")
    assert (
        proc.returncode != 0 and "SDSSJ0946+1006_npix100.npy not found" in proc.stdout + proc.stderr
    )
    after = {p: p.stat().st_mtime for p in resources.rglob("*") if p.is_file()}
    assert after == before
    proc = run_snakemake(root, "--cores", "1", *TINY, mirror=data_dir)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Nothing to be done" in run_snakemake(root, "-n", *TINY, mirror=data_dir).stdout


@pytest.mark.slow
def test_a_failed_rerun_keeps_the_previous_results(finished_campaign, data_dir):
    """A corrupt training shard: the forced rerun of training fails naming the image, and
    model.pt and everything after it are the previous run's, byte for byte."""
    root = finished_campaign
    results = root / "results"
    kept = {
        p: p.read_bytes()
        for p in [
            results / "train_estimator" / "model.pt",
            results / "analyze_hst" / "intervals.csv",
        ]
    }
    shard = results / "simulate_shard" / "train" / "shard_0.h5"
    times = (shard.stat().st_atime, shard.stat().st_mtime)
    _flip_chunk(shard, "images", 1)
    os.utime(shard, times)  # a silent corruption: the whitening is not recomputed
    proc = run_snakemake(root, "--cores", "1", *TINY, "-R", "train_estimator", mirror=data_dir)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0
    log = (root / "logs" / "train_estimator.log").read_text()
    assert re.search(r"train/shard_0.h5: images image 1 cannot be read", log), log[-2000:]
    assert "Restored previous version of results/train_estimator/model.pt" in out, out[-3000:]
    for path, data in kept.items():
        assert path.read_bytes() == data, path
    # a bad input of the HST analysis: the previous intervals and figures stay
    thresholds = results / "summarize_coverage" / "thresholds.json"
    thresholds.write_text("{not json")
    figure = results / "figures" / "fig6_hst_combined.png"
    fig_bytes = figure.read_bytes()
    proc = run_snakemake(
        root, "--cores", "1", *TINY, "-R", "analyze_hst", "--until", "analyze_hst", mirror=data_dir
    )
    assert proc.returncode != 0
    assert figure.read_bytes() == fig_bytes
    assert (results / "analyze_hst" / "intervals.csv").read_bytes() == kept[
        results / "analyze_hst" / "intervals.csv"
    ]


@pytest.mark.slow
def test_a_job_that_fails_after_a_config_change_runs_again(finished_campaign, data_dir):
    """Training fails after training.max_epochs changed: Snakemake puts the previous
    model back, and the next plain run trains again (it would otherwise take the old
    model for one of the new config); the model it writes is the new config's."""
    root = finished_campaign
    results = root / "results"
    old_model = (results / "train_estimator" / "model.pt").read_bytes()
    overlay = root / "config" / "more_epochs.yaml"
    overlay.write_text("training:\n  max_epochs: 3\n  early_stop_patience: 3\n")
    shard = results / "simulate_shard" / "train" / "shard_0.h5"
    good, times = shard.read_bytes(), (shard.stat().st_atime, shard.stat().st_mtime)
    _flip_chunk(shard, "images", 1)
    os.utime(shard, times)  # a silent corruption: the job fails, its inputs look unchanged
    argv = ("--cores", "1", *TINY, str(overlay), "--until", "train_estimator")
    proc = run_snakemake(root, *argv, mirror=data_dir)
    assert proc.returncode != 0
    assert (
        "Restored previous version of results/train_estimator/model.pt" in proc.stdout + proc.stderr
    )
    assert (results / "train_estimator" / "model.pt").read_bytes() == old_model
    shard.write_bytes(good)
    os.utime(shard, times)
    dry = run_snakemake(
        root, "-n", *TINY, str(overlay), "--until", "train_estimator", mirror=data_dir
    )
    assert "train_estimator" in dry.stdout, dry.stdout[-2000:]
    proc = run_snakemake(root, *argv, mirror=data_dir)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    import torch

    model = torch.load(results / "train_estimator" / "model.pt", weights_only=True)
    assert model["config"]["max_epochs"] == 3
    dry = run_snakemake(
        root, "-n", *TINY, str(overlay), "--until", "train_estimator", mirror=data_dir
    )
    assert "Nothing to be done" in dry.stdout or re.search(r"total\s+0\n", dry.stdout), dry.stdout


@pytest.mark.slow
def test_results_get_the_users_umask(tiny_run):
    umask = os.umask(0)
    os.umask(umask)
    mode = 0o666 & ~umask
    # (the variants of test_systematics may be writing into the campaign's shard cache:
    # their temporaries, of mode 0600 until renamed, are not results)
    files = [
        p
        for p in tiny_run.rglob("*")
        if p.is_file() and "checkpoints" not in p.parts and not _temporary(p)
    ]
    assert len(files) > 40
    wrong = [str(p) for p in files if stat.S_IMODE(p.stat().st_mode) != mode]
    assert not wrong, wrong[:5]


def _temporary(path: Path) -> bool:
    """A temporary of subslope.io.atomic (``.<name>.<host>.<pid>.<random>.tmp``)."""
    return path.name.startswith(".") and path.name.endswith(".tmp")


def test_slurm_profile_avoids_the_plugin_failure_modes():
    """Job states from squeue (sacct hangs without accounting), no job arrays (a failed
    task costs the finished shards of the others), resources from the config."""
    profile = yaml.safe_load((REPO_ROOT / "profiles" / "slurm" / "config.yaml").read_text())
    assert profile["slurm-status-command"] == "squeue"
    assert "slurm-array-jobs" not in profile
    for rule, res_ in profile.get("set-resources", {}).items():
        assert not {"mem_mb", "cpus_per_task", "gpu"} & set(res_ or {}), rule


def test_gpu_request_on_a_cluster_without_gpus():
    from subslope import config as cfg
    from subslope.plan import slurm_gpu_problems

    config = cfg.load(TINY_YAML, env=False)
    assert slurm_gpu_problems(config, gres="(null)\n") == []  # tiny asks for no GPU
    config["training"]["gpus"] = 1
    (problem,) = slurm_gpu_problems(config, gres="(null)\n(null)\n")
    assert problem.startswith("config key training.gpus = 1: the SLURM cluster offers no GPU")
    assert slurm_gpu_problems(config, gres="gpu:a100:4\n(null)\n") == []
    config["stages"]["train"] = False
    assert slurm_gpu_problems(config, gres="(null)") == []


def test_local_device_check_imports_torch_only_for_cuda(monkeypatch):
    from subslope.devices import device_problems

    assert device_problems({"training": {"device": "cpu"}, "inference": {"device": "auto"}}) == []
    if not torch.cuda.is_available():
        (problem,) = device_problems({"inference": {"device": "cuda:1"}})
        assert "inference.device = 'cuda:1'" in problem
        assert device_problems({"inference": {"device": "cuda"}}, {"evaluate": False}) == []
