"""Data-parallel training: the process group, each rank's share of a batch, the loss
and batch norm over the whole batch, and the launch of ``training.ranks`` processes with
``torchrun`` (docs/estimator.md, "Training on several GPUs").

Every rank holds the whole model and takes a contiguous share of every global batch of
``batch_size`` images (``ShardBatches.part`` reads only its rows; ``StreamBatches.part``
simulates only its images, from seeds of its own). The step is that of one process on
the whole batch:

- the negatives pair each image with the γ of the *global* batch's permutation (the
  ranks' γ are gathered, a few bytes a step);
- batch norm normalises with the statistics of the whole batch (``SyncBatchNorm`` on
  CUDA; :class:`AllReduceBatchNorm2d` on CPU, where torch's has no kernel);
- each rank's loss is its images' share of the global mean times the number of ranks,
  so the gradients DistributedDataParallel averages are those of the global loss;
- the D₄ augmentation draws the elements of the whole batch and uses the share's.

With a fixed seed, two gloo ranks on CPU end with the weights of one process to float
tolerance (tests/test_distributed.py). Rank 0 alone writes checkpoints, logs and
``model.pt``; every rank reads ``last.pt`` to resume, so a resumed run continues where
all ranks stopped.
"""

from __future__ import annotations

import functools
import json
import os
import re
import subprocess
import sys
from dataclasses import dataclass
from datetime import timedelta

import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import nn

__all__ = [
    "Ranks",
    "AllReduceBatchNorm2d",
    "setup_ranks",
    "rank_device",
    "share_loss",
    "close_ranks",
    "sync_batch_norm",
    "gather_labels",
    "global_mean",
    "RankDiedError",
    "die_with_parent",
    "launch",
]

#: The thread counts a job's environment sets (Snakemake sets each to the job's threads):
#: CPU ranks get 1 of each, so their results do not depend on the job's size.
THREAD_VARIABLES = (
    "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS",
)  # fmt: skip

#: Minutes a rank waits for the others in a collective before it fails (a dead rank
#: otherwise stalls the survivors for torch's default 30 minutes).
COLLECTIVE_TIMEOUT_MIN = 10


@dataclass(frozen=True)
class Ranks:
    """This process's place among the training processes."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        """True on the one process that writes (rank 0)."""
        return self.rank == 0

    def share(self, n: int) -> tuple[int, int]:
        """``(start, stop)`` of this rank's contiguous share of ``n`` rows."""
        return self.rank * n // self.size, (self.rank + 1) * n // self.size

    def barrier(self) -> None:
        if self.size > 1:
            dist.barrier()


def die_with_parent(parent: int | None = None) -> None:
    """Have the kernel SIGKILL this process when its parent dies (Linux
    ``prctl(PR_SET_PDEATHSIG)``; elsewhere nothing): a training job killed outright then
    takes torchrun, and torchrun its ranks, instead of leaving them to write into outputs
    that Snakemake has put back. ``parent``: the pid the parent had when it started this
    process; if it is gone already, this process exits at once."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes
    import signal

    pr_set_pdeathsig = 1
    ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, int(signal.SIGKILL), 0, 0, 0)
    if os.getppid() != (parent or os.getppid()) or os.getppid() == 1:
        os._exit(1)  # the parent died before the request was made


def setup_ranks(device: torch.device) -> Ranks:
    """Join the process group that ``torchrun`` describes (``RANK``, ``WORLD_SIZE``,
    ``LOCAL_RANK``, ``MASTER_ADDR``/``PORT``): NCCL on CUDA, gloo on CPU. One process
    without those variables is rank 0 of 1 and joins nothing."""
    size = int(os.environ.get("WORLD_SIZE", "1"))
    if size == 1:
        return Ranks()
    die_with_parent()  # torchrun's worker: gone with it
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    if device.type == "cpu":
        torch.set_num_threads(1)
    if not dist.is_initialized():
        dist.init_process_group(
            "nccl" if device.type == "cuda" else "gloo",
            timeout=timedelta(minutes=COLLECTIVE_TIMEOUT_MIN),
        )
    return Ranks(rank, size, local)


def close_ranks(ranks: Ranks) -> None:
    if ranks.size > 1 and dist.is_initialized():
        dist.destroy_process_group()


def rank_device(cfg, device: torch.device, ranks: Ranks) -> torch.device:
    """This rank's device (its own GPU on CUDA), after checking that the training can be
    split over the ranks as one process would run it."""
    if cfg["batch_size"] % ranks.size:
        raise ValueError(
            f"training.batch_size = {cfg['batch_size']} must be a multiple of "
            f"training.ranks = {ranks.size} (each rank takes an equal share of every batch)"
        )
    if cfg["bnre_lambda"]:
        raise ValueError(
            f"training.bnre_lambda = {cfg['bnre_lambda']}: the balance penalty is not split "
            "over ranks; use training.ranks: 1 or bnre_lambda: 0"
        )
    if device.type != "cuda":
        return device
    torch.cuda.set_device(ranks.local_rank)
    return torch.device("cuda", ranks.local_rank)


class AllReduceBatchNorm2d(nn.BatchNorm2d):
    """``BatchNorm2d`` whose training statistics are those of the images of every rank
    (two all-reduces through autograd: the mean, then the squared deviations), for CPU
    process groups. In evaluation it is ``BatchNorm2d``."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not (self.training and dist.is_initialized() and dist.get_world_size() > 1):
            return super().forward(x)
        from torch.distributed.nn.functional import all_reduce

        count = torch.tensor(float(x.numel() // x.shape[1]), dtype=x.dtype)
        total = all_reduce(torch.cat([x.sum((0, 2, 3)), count.reshape(1)]))
        n = total[-1]
        if n < 2:  # as BatchNorm2d: no variance from one value (the running one would be inf)
            raise ValueError(f"expected more than 1 value per channel in training, got {int(n)}")
        mean = total[:-1] / n
        centred = x - mean[None, :, None, None]
        var = all_reduce((centred * centred).sum((0, 2, 3))) / n
        with torch.no_grad():
            m = self.momentum if self.momentum is not None else 0.1
            self.running_mean.mul_(1 - m).add_(m * mean.detach())
            self.running_var.mul_(1 - m).add_(m * var.detach() * n / (n - 1))
            self.num_batches_tracked += 1
        y = centred * torch.rsqrt(var + self.eps)[None, :, None, None]
        return y * self.weight[None, :, None, None] + self.bias[None, :, None, None]


def sync_batch_norm(model: nn.Module, device: torch.device) -> nn.Module:
    """``model`` with every ``BatchNorm2d`` normalising over the whole global batch."""
    if device.type == "cuda":
        return nn.SyncBatchNorm.convert_sync_batchnorm(model)
    for name, child in model.named_children():
        if type(child) is nn.BatchNorm2d:
            new = AllReduceBatchNorm2d(child.num_features, child.eps, child.momentum)
            new.load_state_dict(child.state_dict())
            setattr(model, name, new.to(child.weight.device))
        else:
            sync_batch_norm(child, device)
    return model


def gather_labels(gamma: torch.Tensor, ranks: Ranks) -> torch.Tensor:
    """The labels of the whole global batch, in rank order (shares are contiguous)."""
    if ranks.size == 1:
        return gamma
    parts = [torch.empty_like(gamma) for _ in range(ranks.size)]
    dist.all_gather(parts, gamma.contiguous())
    return torch.cat(parts)


def global_mean(value: torch.Tensor, ranks: Ranks) -> float:
    """The mean over the ranks of a scalar (each rank's loss term)."""
    if ranks.size == 1:
        return float(value)
    v = value.detach().clone()
    dist.all_reduce(v)
    return float(v) / ranks.size


def share_loss(
    estimator, gamma_all: torch.Tensor, x: torch.Tensor, pi: torch.Tensor, ranks: Ranks
) -> torch.Tensor:
    """This rank's term of the NRE loss of the global batch: its images against their γ
    (positives) and the γ the global permutation ``pi`` gives them (negatives), as
    ``ranks.size`` × their share of the global mean (the averaged gradients are then
    the global loss's). Plain NRE only (BNRE's penalty is not a sum over images)."""
    start, stop = ranks.share(gamma_all.shape[0])
    log_r = estimator(torch.stack((gamma_all[start:stop], gamma_all[pi][start:stop])), x)
    b = gamma_all.shape[0]
    terms = F.softplus(-log_r[0]).sum() + F.softplus(log_r[1]).sum()
    return 0.5 * terms / b * ranks.size


class RankDiedError(RuntimeError):
    """A rank of a data-parallel training ended with an error or was killed."""


def launch(job: dict, ranks: int, *, module: str, device_type: str) -> None:
    """Run ``python -m module JSON(job)`` as ``ranks`` processes with ``torchrun
    --standalone`` (the workflow: :mod:`subslope.stages.train`, each rank calling its
    ``run_training``); raises
    :class:`RankDiedError` naming the rank that failed first (its exit code or signal) when
    one does, after torchrun has stopped the others. A rerun resumes from the last
    checkpoint. torchrun and the ranks die with this process (:func:`die_with_parent`),
    however it ends."""
    command = [
        sys.executable, "-m", "torch.distributed.run", "--standalone",
        f"--nproc-per-node={int(ranks)}", "-m", module, json.dumps(job),
    ]  # fmt: skip
    env = dict(os.environ)
    if device_type == "cpu":  # one CPU thread per rank, whatever the job's environment
        for name in THREAD_VARIABLES:  # says: the sums then run in one order everywhere
            env[name] = "1"
    proc = subprocess.Popen(
        command,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=functools.partial(die_with_parent, os.getpid()),
    )
    lines = []
    assert proc.stdout is not None
    for line in proc.stdout:  # the ranks' output, passed on as it comes
        sys.stderr.write(line)
        lines.append(line)
    if proc.wait() != 0:
        raise RankDiedError(_death_message("".join(lines[-400:]), proc.returncode, ranks))


def _death_message(stderr: str, code: int, ranks: int) -> str:
    """Which rank failed, from torchrun's report ("rank : 1 (local_rank: 1)" and its
    exitcode), and how to go on."""
    root = stderr[stderr.rfind("Root Cause") :] if "Root Cause" in stderr else stderr
    found = re.search(r"rank\s*:\s*(\d+).*?exitcode\s*:\s*(-?\d+)", root, re.S)
    if found is None:
        who = f"a rank of {ranks} (torchrun exit {code})"
    else:
        rank, exit_code = int(found.group(1)), int(found.group(2))
        how = f"signal {-exit_code}" if exit_code < 0 else f"exit code {exit_code}"
        who = f"rank {rank} of {ranks} ({how})"
    return (
        f"data-parallel training stopped: {who} ended first and torchrun stopped the others; "
        "run the job again to resume from the last checkpoint (rank 0 writes it)"
    )
