"""Data-parallel training on CPU with two gloo ranks: the weights of one process with the
same global batch, a stop and resume, and a rank that dies."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import torch
from test_nre_data import write_shard

from subslope.nre.checkpoints import torch_load
from subslope.nre.distributed import RankDiedError, launch
from subslope.nre.train import train

TINY = {"depth": 10, "width": 0.0625, "head": [16]}
WHITENING = (11.0, 3.0)

#: One rank: train() as torchrun starts it.
RANK_SCRIPT = """
import json, sys
from subslope.nre.train import train
a = json.loads(sys.argv[1])
train(a["cfg"], a["tr"], a["va"], tuple(a["w"]), a["out"], a["ck"], device="cpu")
"""


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    d = tmp_path_factory.mktemp("ddp_shards")
    tr = [
        write_shard(d / "t0.h5", 45, 0, hw=32, signal=3.0),
        write_shard(d / "t1.h5", 38, 1, hw=32, signal=3.0, offset=45),
    ]
    return [str(p) for p in tr], [str(write_shard(d / "v0.h5", 24, 2, hw=32, signal=3.0))]


def _cfg(**kw):
    cfg = {"arch": TINY, "batch_size": 16, "max_epochs": 2, "deterministic": True,
           "progress": False, "block_size": 8, "seed": 3, "augment": "dihedral",
           "negatives": "derangement", "checkpoint_every": 1}  # fmt: skip
    return {**cfg, **kw}


def _two_ranks(tmp_path: Path, shards, cfg, name: str) -> Path:
    script = tmp_path / "rank.py"
    script.write_text(RANK_SCRIPT)
    ck = tmp_path / f"{name}_ck"
    args = {"cfg": cfg, "tr": shards[0], "va": shards[1], "w": list(WHITENING),
            "out": str(tmp_path / f"{name}_out"), "ck": str(ck)}  # fmt: skip
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone",
               "--nproc-per-node=2", str(script), json.dumps(args)]  # fmt: skip
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return ck


def _weights(ck: Path) -> dict[str, torch.Tensor]:
    return torch_load(ck / "last.pt", "cpu", "test")["model"]


def _assert_close(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for name in a:
        if a[name].is_floating_point():
            torch.testing.assert_close(a[name], b[name], rtol=1e-4, atol=1e-5, msg=name)
        else:
            assert torch.equal(a[name], b[name]), name


@pytest.mark.slow
def test_two_ranks_train_as_one_process_and_resume(shards, tmp_path):
    one = tmp_path / "one_ck"
    summary = train(_cfg(max_steps=4), *shards, WHITENING, tmp_path / "one_out", one, device="cpu")
    assert summary["step"] == 4
    two = _two_ranks(tmp_path, shards, _cfg(max_steps=4), "two")
    _assert_close(_weights(one), _weights(two))  # batch norm over both ranks' images
    state = torch_load(two / "last.pt", "cpu", "test")["state"]
    assert state["step"] == 4 and state["loss_count"] == 4 * 16  # the global batch
    # stopped after 2 steps and resumed: the weights of the uninterrupted two ranks
    _two_ranks(tmp_path, shards, _cfg(max_steps=2), "resumed")
    resumed = _two_ranks(tmp_path, shards, _cfg(max_steps=4), "resumed")
    _assert_close(_weights(two), _weights(resumed))
    assert not (tmp_path / "two_out" / "model.pt").exists()  # not finished: no artifact


def _rank_pid(parent: int, rank: int) -> int | None:
    """The pid of the torchrun worker with RANK=rank among the descendants of parent."""
    for status in Path("/proc").glob("[0-9]*/environ"):
        try:
            env = status.read_bytes().split(b"\0")
        except OSError:
            continue
        if f"RANK={rank}".encode() in env and f"SUBSLOPE_TEST_PARENT={parent}".encode() in env:
            return int(status.parent.name)
    return None


def _long_job(shards, tmp_path) -> dict:
    """A training job of 40 epochs with a checkpoint every epoch: long enough to be
    interrupted once its first checkpoint is written."""
    whitening = tmp_path / "whitening.json"
    whitening.write_text(json.dumps({"mean": WHITENING[0], "std": WHITENING[1]}))
    return {"training": _cfg(max_epochs=40, checkpoint_every=1, seed=5, early_stop_patience=40),
            "train_shards": shards[0], "val_shards": shards[1], "whitening": str(whitening),
            "out_dir": str(tmp_path / "out"), "ckpt_dir": str(tmp_path / "ck")}  # fmt: skip


@pytest.mark.slow
def test_a_rank_that_dies_is_named_and_a_rerun_resumes(shards, tmp_path):
    job = _long_job(shards, tmp_path)
    os.environ["SUBSLOPE_TEST_PARENT"] = str(os.getpid())
    errors: list[BaseException] = []

    def run():
        try:
            launch(job, 2, module="subslope.stages.train", device_type="cpu")
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            errors.append(exc)

    thread = threading.Thread(target=run)
    thread.start()
    ckpt = None
    deadline = time.time() + 300
    while time.time() < deadline and ckpt is None:
        found = list((tmp_path / "ck").rglob("last.pt"))
        ckpt = found[0] if found else None
        time.sleep(0.5)
    assert ckpt is not None, "no checkpoint written"
    pid = _rank_pid(os.getpid(), 1)
    assert pid is not None
    os.kill(pid, signal.SIGKILL)
    thread.join(timeout=300)
    del os.environ["SUBSLOPE_TEST_PARENT"]
    assert errors and isinstance(errors[0], RankDiedError), errors
    assert "rank 1 of 2 (signal 9)" in str(errors[0])
    assert "resume from the last checkpoint" in str(errors[0])
    step = torch_load(ckpt, "cpu", "test")["state"]["step"]
    job["training"]["max_epochs"] = 3  # a resume-safe change, so the rerun ends soon
    launch(job, 2, module="subslope.stages.train", device_type="cpu")
    assert (tmp_path / "out" / "model.pt").is_file()
    assert torch_load(ckpt, "cpu", "test")["state"]["step"] > step


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie left to a container's init counts as gone)."""
    try:
        state = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    return "\nState:\tZ" not in state


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_killed_job_takes_torchrun_and_its_ranks_with_it(shards, tmp_path):
    job = _long_job(shards, tmp_path)
    marker = f"killed-{os.getpid()}"
    code = (
        "import json, sys\nfrom subslope.nre.distributed import launch\n"
        "launch(json.loads(sys.argv[1]), 2, module='subslope.stages.train', device_type='cpu')"
    )
    env = dict(os.environ, SUBSLOPE_TEST_PARENT=marker)
    proc = subprocess.Popen([sys.executable, "-c", code, json.dumps(job)], env=env)
    deadline = time.time() + 300
    while time.time() < deadline and not list((tmp_path / "ck").rglob("last.pt")):
        assert proc.poll() is None, "the training ended before it could be killed"
        time.sleep(0.5)
    ranks = [_rank_pid(marker, r) for r in (0, 1)]
    assert None not in ranks, "the ranks did not start"
    proc.kill()  # the job's own process, as a cluster's OOM killer or kill -9 would
    proc.wait()
    deadline = time.time() + 60
    while time.time() < deadline and any(_alive(p) for p in ranks):
        time.sleep(0.5)
    assert not any(_alive(p) for p in ranks), "ranks outlived their job"
    left = [
        status.parent.name
        for status in Path("/proc").glob("[0-9]*/environ")
        if _alive(int(status.parent.name)) and _environ_has(status, marker)
    ]
    assert not left, f"processes of the killed job still run: {left}"


def _environ_has(path: Path, marker: str) -> bool:
    try:
        return f"SUBSLOPE_TEST_PARENT={marker}".encode() in path.read_bytes()
    except OSError:
        return False
