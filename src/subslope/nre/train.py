"""Training of the ratio estimator: resumable loop, checkpoints and the ``model.pt`` artifact.

Objective: the NRE loss of :mod:`subslope.nre.loss` on batches streamed by
:mod:`subslope.nre.data`, optimised with AdamW; ``ReduceLROnPlateau`` (×0.1 after
``lr_patience`` stagnant epochs, ``lr_cooldown`` epochs of cool-down) on the validation
loss; training stops when the validation loss has not improved on its best value by
more than ``min_delta`` for ``early_stop_patience`` consecutive epochs, or at
``max_epochs`` (docs/estimator.md).

Checkpoints (``ckpt_dir``, kept outside the workflow's declared outputs):

- ``last.pt`` — written atomically (temporary file + ``os.replace``) at the end of every
  epoch and every ``checkpoint_every`` optimiser steps: model, optimiser, scheduler and
  grad-scaler states, torch/numpy/python RNG states, the position in the data order
  (epoch, batch within the epoch, global step), early-stopping state, running sums of
  the current epoch and the history of finished epochs.
- ``best.pt`` — the weights with the lowest validation loss so far.

Calling :func:`train` again with the same ``ckpt_dir`` resumes from ``last.pt``: the data
loader restarts at the next batch of the interrupted epoch, so with ``deterministic:
true`` on CPU a resumed run ends with the same weights as an uninterrupted one. Keys in
:data:`RESUME_SAFE_KEYS` may change between the interrupted and the resumed call; any
other change of the training section raises ``ValueError`` (delete ``ckpt_dir`` to start
afresh).

``out_dir/model.pt`` (written at the end, from ``best.pt``) holds the weights, the model
card, the whitening statistics, the γ normalisation, the resolved training section and
its hash, and the training log; :func:`load_estimator` rebuilds the model from it.
"""

from __future__ import annotations

import logging
import math
import os
import random
import sys
import time
from collections.abc import Mapping, Sequence
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from subslope.devices import pick_device

from .artifacts import summary, write_log, write_model
from .augment import random_dihedral, step_generator
from .checkpoints import (
    CheckpointError,
    atomic_save,
    load_estimator,
    rng_state,
    set_rng_state,
    torch_load,
)
from .data import ShardBatches, make_loader, read_labels
from .distributed import (
    Ranks,
    close_ranks,
    gather_labels,
    global_mean,
    rank_device,
    setup_ranks,
    share_loss,
    sync_batch_norm,
)
from .loss import NRELoss, negative_indices
from .models import RatioEstimator, build_model
from .preprocess import read_inputs, read_whitening
from .stream import StreamBatches
from .training_config import RESUME_SAFE_KEYS, config_hash, resolve_config

__all__ = [
    "CheckpointError",
    "resolve_config",
    "config_hash",
    "train",
    "load_estimator",
    "evaluate",
]


log = logging.getLogger(__name__)


def _amp_dtype(cfg, device: torch.device) -> torch.dtype | None:
    if device.type != "cuda" or cfg["amp"] == "off":
        return None
    if cfg["amp"] == "bf16" or (cfg["amp"] == "auto" and torch.cuda.is_bf16_supported()):
        return torch.bfloat16
    return torch.float16


@torch.no_grad()
def evaluate(
    model: RatioEstimator,
    dataset: ShardBatches,
    loss_fn: NRELoss,
    device: torch.device,
    *,
    num_workers: int = 0,
    amp_dtype=None,
) -> float:
    """Mean NRE loss over a dataset (eval mode, file order, roll negatives)."""
    was_training = model.training
    model.eval()
    total, count = 0.0, 0
    for batch in make_loader(dataset, num_workers=num_workers, pin_memory=device.type == "cuda"):
        n = batch["x"].shape[0]
        if n < 2:
            continue
        x, g = (
            batch["x"].to(device, non_blocking=True),
            batch["gamma"].to(device, non_blocking=True),
        )
        ctx = (
            torch.autocast(device.type, dtype=amp_dtype) if amp_dtype is not None else nullcontext()
        )
        with ctx:
            loss = loss_fn(g, x)
        total += float(loss) * n
        count += n
    model.train(was_training)
    if count == 0:
        raise ValueError(f"validation shards {dataset.paths} give no batch of at least 2 images")
    return total / count


def train(
    config: Mapping[str, Any] | None,
    train_shards: Sequence,
    val_shards: Sequence,
    whitening,
    out_dir,
    ckpt_dir,
    *,
    device=None,
) -> dict[str, Any]:
    """Train (or resume training) the ratio estimator and write ``out_dir/model.pt``.

    Parameters
    ----------
    config: the ``training:`` section (:func:`subslope.nre.training_config.training_defaults`
        fills missing keys).
    train_shards: HDF5 shard paths, or a :class:`subslope.nre.stream.StreamBatches` of
        images simulated while training (``training.data: stream``; its batch size must be
        ``batch_size``).
    val_shards: HDF5 shard paths.
    whitening: ``(mean, std)``, a mapping or the whitening JSON path.
    out_dir: receives ``model.pt`` and ``training_log.csv``.
    ckpt_dir: checkpoints (``last.pt``, ``best.pt``); resumed from when present.
    device: torch device; default CUDA if available, else CPU.

    Returns a summary dict: ``finished`` (False when stopped by ``max_steps``), ``model``
    (path of ``model.pt`` or None), ``epochs``, ``step``, ``best_val_loss``, ``stop_reason``.
    """
    cfg = resolve_config(config)
    chash = config_hash(cfg)
    device = pick_device(device, key="training.device")
    ranks = setup_ranks(device)
    if ranks.size > 1:
        device = rank_device(cfg, device, ranks)
    inputs = read_inputs(whitening, expect=cfg["inputs"])
    whitening = read_whitening(whitening)
    out_dir, ckpt_dir = Path(out_dir), Path(ckpt_dir)
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    last_path, best_path = ckpt_dir / "last.pt", ckpt_dir / "best.pt"
    amp_dtype = _amp_dtype(cfg, device)

    prev_det = torch.are_deterministic_algorithms_enabled()
    prev_bench = torch.backends.cudnn.benchmark
    if cfg["deterministic"]:
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True)
        torch.backends.cudnn.benchmark = False
    elif device.type == "cuda":
        torch.backends.cudnn.benchmark = True
    try:
        return _train(
            cfg,
            chash,
            train_shards,
            val_shards,
            (whitening, inputs),
            out_dir,
            ckpt_dir,
            (last_path, best_path),
            (device, ranks),
            amp_dtype,
        )
    finally:
        torch.use_deterministic_algorithms(prev_det)
        torch.backends.cudnn.benchmark = prev_bench
        close_ranks(ranks)


@dataclass
class _Run:
    """Everything one training run carries between its steps."""

    cfg: dict[str, Any]
    chash: str
    model: RatioEstimator
    opt: Any
    sched: Any
    scaler: Any
    loss_fn: NRELoss
    val_loss_fn: NRELoss
    device: torch.device
    amp_dtype: torch.dtype | None
    last_path: Path
    best_path: Path
    ranks: Ranks = field(default_factory=Ranks)
    forward: Any = None  # the model the loss calls (DistributedDataParallel with ranks)
    state: dict[str, Any] = field(
        default_factory=lambda: {
            "epoch": 0,
            "batch_in_epoch": 0,
            "step": 0,
            "best_val": math.inf,
            "bad_epochs": 0,
            "history": [],
            "loss_sum": 0.0,
            "loss_count": 0,
            "train_seconds": 0.0,
            "finished": False,
            "stop_reason": None,
        }
    )

    def checkpoint(self) -> None:
        """Rank 0 writes ``last.pt``; every rank waits for it."""
        if self.ranks.main:
            self._write_last()
        self.ranks.barrier()

    def _write_last(self) -> None:
        atomic_save(
            {
                "config": self.cfg,
                "config_hash": self.chash,
                "model": self.model.state_dict(),
                "optimizer": self.opt.state_dict(),
                "scheduler": self.sched.state_dict(),
                "scaler": self.scaler.state_dict() if self.scaler is not None else None,
                "rng": rng_state(),
                "state": self.state,
            },
            self.last_path,
        )


def _start(cfg, chash, train_shards, placement, amp_dtype, paths) -> _Run:
    """Seed every generator, build the model, optimiser, scheduler and losses (with
    several ranks: batch norm over the whole batch, DistributedDataParallel)."""
    device, ranks = placement
    labels = (
        train_shards.labels()
        if isinstance(train_shards, StreamBatches)
        else read_labels(train_shards)
    )
    gamma_mean, gamma_std = float(labels.mean()), float(labels.std())
    if not gamma_std > 0:
        raise ValueError(
            f"training labels params/gamma_sub have zero spread (all {gamma_mean}); need varied γ"
        )
    seed = int(cfg["seed"])
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)
    random.seed(seed)
    model = build_model(cfg["arch"], gamma_mean=gamma_mean, gamma_std=gamma_std).to(device)
    forward = model
    if ranks.size > 1:
        model = sync_batch_norm(model, device)
        forward = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None
        )
    opt = torch.optim.AdamW(model.parameters(), lr=cfg["lr"], weight_decay=cfg["weight_decay"])
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(
        opt,
        mode="min",
        factor=cfg["lr_factor"],
        patience=cfg["lr_patience"],
        cooldown=cfg["lr_cooldown"],
        threshold=cfg["min_delta"],
        threshold_mode="abs",
    )
    scaler = torch.amp.GradScaler("cuda") if amp_dtype == torch.float16 else None
    loss_fn = NRELoss(model, lmbda=cfg["bnre_lambda"], negatives=cfg["negatives"])
    val_loss_fn = NRELoss(
        model, lmbda=cfg["bnre_lambda"], negatives="roll"
    )  # a fixed function of the weights
    return _Run(
        cfg,
        chash,
        model,
        opt,
        sched,
        scaler,
        loss_fn,
        val_loss_fn,
        device,
        amp_dtype,
        *paths,
        ranks,
        forward,
    )


def _resume(run: _Run, ckpt_dir) -> None:
    """Continue from ``last.pt`` when it exists: weights, optimiser, scheduler, scaler,
    random states and the loop position."""
    if not run.last_path.exists():
        return
    ck = torch_load(
        run.last_path,
        run.device,
        f"delete {ckpt_dir} to train afresh (a checkpoint written whole is never replaced by "
        "a partial one: this file was changed after it was written)",
    )
    cfg = run.cfg
    if ck["config_hash"] != run.chash:
        changed = sorted(
            k for k in cfg if k not in RESUME_SAFE_KEYS and ck["config"].get(k) != cfg[k]
        )
        raise ValueError(
            f"checkpoint {run.last_path} was written with a different training config "
            f"(changed: {changed}); delete {ckpt_dir} to start afresh"
        )
    run.model.load_state_dict(ck["model"])
    run.opt.load_state_dict(ck["optimizer"])
    run.sched.load_state_dict(ck["scheduler"])
    if run.scaler is not None and ck.get("scaler"):
        run.scaler.load_state_dict(ck["scaler"])
    set_rng_state(ck["rng"])
    run.state.update(ck["state"])
    if run.state["finished"]:
        run.state["stop_reason"] = run.state.get("stop_reason") or "finished"
    log.info(
        "resumed from %s at epoch %d, batch %d, step %d",
        run.last_path,
        run.state["epoch"],
        run.state["batch_in_epoch"],
        run.state["step"],
    )


def _step(run: _Run, batch, pin: bool) -> int:
    """One optimiser step on ``batch``; returns the number of images."""
    x = batch["x"].to(run.device, non_blocking=pin)
    g = batch["gamma"].to(run.device, non_blocking=pin)
    if run.cfg["augment"] == "dihedral":  # the global batch's draw, this rank's share
        n_all = x.shape[0] * run.ranks.size
        gen = step_generator(run.cfg["seed"], run.state["step"])
        x = random_dihedral(x, gen, start=run.ranks.share(n_all)[0], total=n_all)
    ctx = (
        torch.autocast(run.device.type, dtype=run.amp_dtype)
        if run.amp_dtype is not None
        else nullcontext()
    )
    if run.ranks.size > 1:
        return _share_step(run, x, g, ctx)
    with ctx:
        loss = run.loss_fn(g, x)
    return _apply(run, loss, loss, x.shape[0])


def _share_step(run: _Run, x, g, ctx) -> int:
    """One step of this rank on its share ``x`` of the global batch (labels ``g``)."""
    ranks = run.ranks
    gamma_all = gather_labels(g, ranks)
    total = gamma_all.shape[0]
    pi = negative_indices(total, run.cfg["negatives"], device=gamma_all.device)
    with ctx:
        loss = share_loss(run.forward, gamma_all, x, pi, ranks)
    return _apply(run, loss, None, total)


def _apply(run: _Run, loss, value, n: int) -> int:
    """Backward and optimiser step; the step's loss (``value``, or the ranks' mean of
    ``loss``) is added to the epoch's sums for ``n`` images."""
    run.opt.zero_grad(set_to_none=True)
    if run.scaler is not None:
        run.scaler.scale(loss).backward()
        run.scaler.step(run.opt)
        run.scaler.update()
    else:
        loss.backward()
        run.opt.step()
    lv = float(value.detach()) if value is not None else global_mean(loss, run.ranks)
    if not math.isfinite(lv):
        raise FloatingPointError(
            f"training loss is {lv} at epoch {run.state['epoch']}, step {run.state['step']}"
        )
    state = run.state
    state["loss_sum"] += lv * n
    state["loss_count"] += n
    state["step"] += 1
    state["batch_in_epoch"] += 1
    return n


def _train_epoch(run: _Run, train_ds, max_steps) -> bool:
    """The rest of the current epoch; True when ``max_steps`` stopped it (checkpointed)."""
    cfg, state = run.cfg, run.state
    pin = run.device.type == "cuda"
    epoch = state["epoch"]
    train_ds.set_epoch(epoch)
    loader = make_loader(
        train_ds, start=state["batch_in_epoch"], num_workers=cfg["num_workers"], pin_memory=pin
    )
    t0 = time.perf_counter()
    bar = tqdm(
        loader,
        total=len(train_ds),
        initial=state["batch_in_epoch"],
        desc=f"epoch {epoch}",
        disable=not cfg["progress"],
        file=sys.stderr,
        dynamic_ncols=True,
        mininterval=2.0,
    )
    for batch in bar:
        _step(run, batch, pin)
        if state["step"] % 20 == 0:
            bar.set_postfix(loss=f"{state['loss_sum'] / state['loss_count']:.4f}", refresh=False)
        stop = max_steps is not None and state["step"] >= max_steps
        if stop or (cfg["checkpoint_every"] and state["step"] % cfg["checkpoint_every"] == 0):
            state["train_seconds"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            run.checkpoint()
        if stop:
            bar.close()
            log.info(
                "stopped at max_steps=%d (epoch %d, batch %d); call train() again to resume",
                max_steps,
                epoch,
                state["batch_in_epoch"],
            )
            return True
    bar.close()
    state["train_seconds"] += time.perf_counter() - t0
    return False


def _end_epoch(run: _Run, val_ds, out_dir: Path) -> None:
    """Validate, step the scheduler, keep the best weights, decide on stopping and
    checkpoint."""
    cfg, state = run.cfg, run.state
    epoch = state["epoch"]
    tv = time.perf_counter()
    val = evaluate(
        run.model,
        val_ds,
        run.val_loss_fn,
        run.device,
        num_workers=cfg["num_workers"],
        amp_dtype=run.amp_dtype,
    )
    val_seconds = time.perf_counter() - tv
    lr = run.opt.param_groups[0]["lr"]
    run.sched.step(val)
    row = {
        "epoch": epoch,
        "train_loss": state["loss_sum"] / max(state["loss_count"], 1),
        "val_loss": val,
        "lr": lr,
        "seconds": state["train_seconds"] + val_seconds,
        "images_per_s": state["loss_count"] / max(state["train_seconds"], 1e-9),
    }
    state["history"].append(row)
    log.info(
        "epoch %d: train %.5f val %.5f lr %.2e (%.1f s, %.0f img/s)",
        epoch,
        row["train_loss"],
        val,
        lr,
        row["seconds"],
        row["images_per_s"],
    )
    best = {"model": run.model.state_dict(), "epoch": epoch, "val_loss": val}
    if val < state["best_val"] - cfg["min_delta"]:
        state["best_val"], state["bad_epochs"] = val, 0
        if run.ranks.main:
            atomic_save(best, run.best_path)
    else:
        state["bad_epochs"] += 1
        if val < state["best_val"]:  # small gain: keep the better weights, still count as stagnant
            state["best_val"] = val
            if run.ranks.main:
                atomic_save(best, run.best_path)
    state.update(epoch=epoch + 1, batch_in_epoch=0, loss_sum=0.0, loss_count=0, train_seconds=0.0)
    if state["bad_epochs"] >= cfg["early_stop_patience"]:
        state["finished"], state["stop_reason"] = True, "early_stop"
    elif state["epoch"] >= cfg["max_epochs"]:
        state["finished"], state["stop_reason"] = True, "max_epochs"
    run.checkpoint()
    if run.ranks.main:
        write_log(state["history"], out_dir / "training_log.csv")


def _train(
    cfg,
    chash,
    train_shards,
    val_shards,
    prep,
    out_dir,
    ckpt_dir,
    paths,
    placement,
    amp_dtype,
):
    whitening, inputs = prep
    run = _start(cfg, chash, train_shards, placement, amp_dtype, paths)
    _resume(run, ckpt_dir)
    state = run.state
    train_ds = _training_batches(cfg, train_shards, whitening, inputs)
    if run.ranks.size > 1:
        train_ds.part = (run.ranks.rank, run.ranks.size)
    val_ds = ShardBatches(
        val_shards,
        cfg["val_batch_size"] or cfg["batch_size"],
        whitening,
        shuffle=False,
        pixel_scale=cfg["pixel_scale"],
        mask_factor=cfg["mask_factor"],
        inputs=inputs,
    )
    if len(train_ds) == 0:
        raise ValueError(
            f"training shards hold {train_ds.n_images} images, fewer than one batch of "
            f"{cfg['batch_size']}"
        )
    max_steps = cfg["max_steps"]
    if max_steps is not None and state["step"] >= max_steps and not state["finished"]:
        return summary(state, None, finished=False)
    run.model.train()
    while not state["finished"]:
        if state["epoch"] >= cfg["max_epochs"]:
            state["finished"], state["stop_reason"] = True, "max_epochs"
            break
        if _train_epoch(run, train_ds, max_steps):
            return summary(state, None, finished=False)
        _end_epoch(run, val_ds, out_dir)
    run.checkpoint()
    model_path = out_dir / "model.pt"
    if run.ranks.main:
        write_model(run, whitening, inputs, out_dir)
        write_log(state["history"], out_dir / "training_log.csv")
    run.ranks.barrier()
    return summary(state, model_path, finished=True)


def _training_batches(cfg, train_shards, whitening, inputs):
    """The training set: the stream as given (with the run's whitening and inputs), or
    the shards shuffled per epoch."""
    if isinstance(train_shards, StreamBatches):
        if train_shards.batch_size != cfg["batch_size"]:
            raise ValueError(
                f"the training stream has batches of {train_shards.batch_size} images, "
                f"training.batch_size is {cfg['batch_size']}"
            )
        train_shards.whitening, train_shards.inputs = whitening, inputs
        train_shards.pixel_scale, train_shards.mask_factor = cfg["pixel_scale"], cfg["mask_factor"]
        return train_shards
    return ShardBatches(
        train_shards,
        cfg["batch_size"],
        whitening,
        shuffle=True,
        seed=int(cfg["seed"]),
        block_size=cfg["block_size"],
        window=cfg["shuffle_window"],
        drop_last=True,
        pixel_scale=cfg["pixel_scale"],
        mask_factor=cfg["mask_factor"],
        inputs=inputs,
    )
