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

import copy
import logging
import math
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
from .training_state import TrainingSetup, TrainingState, deterministic_torch

__all__ = [
    "CheckpointError",
    "resolve_config",
    "config_hash",
    "train",
    "load_estimator",
    "validation_loss",
]


log = logging.getLogger(__name__)


def _amp_dtype(cfg, device: torch.device) -> torch.dtype | None:
    if device.type != "cuda" or cfg["amp"] == "off":
        return None
    if cfg["amp"] == "bf16" or (cfg["amp"] == "auto" and torch.cuda.is_bf16_supported()):
        return torch.bfloat16
    return torch.float16


@torch.no_grad()
def validation_loss(
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
        ``batch_size``); a stream is not changed (the run trains on a copy).
    val_shards: HDF5 shard paths.
    whitening: ``(mean, std)``, a mapping or the whitening JSON path.
    out_dir: receives ``model.pt`` and ``training_log.csv``.
    ckpt_dir: checkpoints (``last.pt``, ``best.pt``); resumed from when present.
    device: torch device; default CUDA if available, else CPU.

    Returns a summary dict: ``finished`` (False when stopped by ``max_steps``), ``model``
    (path of ``model.pt`` or None), ``epochs``, ``step``, ``best_val_loss``, ``stop_reason``.
    """
    cfg = resolve_config(config)
    device = pick_device(device, key="training.device")
    ranks = setup_ranks(device)
    if ranks.size > 1:
        device = rank_device(cfg, device, ranks)
    setup = TrainingSetup(
        cfg=cfg,
        chash=config_hash(cfg),
        device=device,
        ranks=ranks,
        amp_dtype=_amp_dtype(cfg, device),
        whitening=read_whitening(whitening),
        inputs=read_inputs(whitening, expect=cfg["inputs"]),
        out_dir=Path(out_dir),
        ckpt_dir=Path(ckpt_dir),
    )
    setup.ckpt_dir.mkdir(parents=True, exist_ok=True)
    try:
        with deterministic_torch(cfg, device):
            return _train(setup, train_shards, val_shards)
    finally:
        close_ranks(ranks)


@dataclass
class _Run:
    """The model, its optimiser and losses, and the state of one training run."""

    setup: TrainingSetup
    model: RatioEstimator
    opt: Any
    sched: Any
    scaler: Any
    loss_fn: NRELoss
    val_loss_fn: NRELoss
    forward: Any  # the model the loss calls (DistributedDataParallel with ranks)
    state: TrainingState = field(default_factory=TrainingState)

    @property
    def cfg(self) -> dict[str, Any]:
        return self.setup.cfg

    @property
    def chash(self) -> str:
        return self.setup.chash

    @property
    def device(self) -> torch.device:
        return self.setup.device

    @property
    def ranks(self) -> Ranks:
        return self.setup.ranks

    @property
    def amp_dtype(self) -> torch.dtype | None:
        return self.setup.amp_dtype

    @property
    def last_path(self) -> Path:
        return self.setup.last_path

    @property
    def best_path(self) -> Path:
        return self.setup.best_path

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
                "state": self.state.as_dict(),
            },
            self.last_path,
        )


def _label_norm(train_shards) -> tuple[float, float]:
    """Mean and standard deviation of the training labels γ (the model's γ scaling)."""
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
    return gamma_mean, gamma_std


def _start(setup: TrainingSetup, train_shards) -> _Run:
    """Seed every generator, build the model, optimiser, scheduler and losses (with
    several ranks: batch norm over the whole batch, DistributedDataParallel)."""
    cfg, device = setup.cfg, setup.device
    gamma_mean, gamma_std = _label_norm(train_shards)
    seed = int(cfg["seed"])
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)
    random.seed(seed)
    model = build_model(cfg["arch"], gamma_mean=gamma_mean, gamma_std=gamma_std).to(device)
    forward = model
    if setup.ranks.size > 1:
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
    scaler = torch.amp.GradScaler("cuda") if setup.amp_dtype == torch.float16 else None
    return _Run(
        setup,
        model,
        opt,
        sched,
        scaler,
        NRELoss(model, lmbda=cfg["bnre_lambda"], negatives=cfg["negatives"]),
        # validation: a fixed function of the weights
        NRELoss(model, lmbda=cfg["bnre_lambda"], negatives="roll"),
        forward,
    )


def _resume(run: _Run) -> None:
    """Continue from ``last.pt`` when it exists: weights, optimiser, scheduler, scaler,
    random states and the loop position."""
    if not run.last_path.exists():
        return
    ckpt_dir = run.setup.ckpt_dir
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
    run.state = TrainingState.from_dict(ck["state"])
    if run.state.finished:
        run.state.stop_reason = run.state.stop_reason or "finished"
    log.info(
        "resumed from %s at epoch %d, batch %d, step %d",
        run.last_path,
        run.state.epoch,
        run.state.batch_in_epoch,
        run.state.step,
    )


def _step(run: _Run, batch, pin: bool) -> int:
    """One optimiser step on ``batch``; returns the number of images."""
    x = batch["x"].to(run.device, non_blocking=pin)
    g = batch["gamma"].to(run.device, non_blocking=pin)
    if run.cfg["augment"] == "dihedral":  # the global batch's draw, this rank's share
        n_all = x.shape[0] * run.ranks.size
        gen = step_generator(run.cfg["seed"], run.state.step)
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
    state = run.state
    if not math.isfinite(lv):
        raise FloatingPointError(f"training loss is {lv} at epoch {state.epoch}, step {state.step}")
    state.loss_sum += lv * n
    state.loss_count += n
    state.step += 1
    state.batch_in_epoch += 1
    return n


def _train_epoch(run: _Run, train_ds, max_steps) -> bool:
    """The rest of the current epoch; True when ``max_steps`` stopped it (checkpointed)."""
    cfg, state = run.cfg, run.state
    pin = run.device.type == "cuda"
    train_ds.set_epoch(state.epoch)
    loader = make_loader(
        train_ds, start=state.batch_in_epoch, num_workers=cfg["num_workers"], pin_memory=pin
    )
    t0 = time.perf_counter()
    bar = tqdm(
        loader,
        total=len(train_ds),
        initial=state.batch_in_epoch,
        desc=f"epoch {state.epoch}",
        disable=not cfg["progress"],
        file=sys.stderr,
        dynamic_ncols=True,
        mininterval=2.0,
    )
    for batch in bar:
        _step(run, batch, pin)
        if state.step % 20 == 0:
            bar.set_postfix(loss=f"{state.loss_sum / state.loss_count:.4f}", refresh=False)
        stop = max_steps is not None and state.step >= max_steps
        if stop or (cfg["checkpoint_every"] and state.step % cfg["checkpoint_every"] == 0):
            state.train_seconds += time.perf_counter() - t0
            t0 = time.perf_counter()
            run.checkpoint()
        if stop:
            bar.close()
            log.info(
                "stopped at max_steps=%d (epoch %d, batch %d); call train() again to resume",
                max_steps,
                state.epoch,
                state.batch_in_epoch,
            )
            return True
    bar.close()
    state.train_seconds += time.perf_counter() - t0
    return False


def _validate(run: _Run, val_ds) -> dict[str, Any]:
    """The validation loss of the epoch that ends, the scheduler stepped on it; the
    epoch's row of the training log."""
    state = run.state
    tv = time.perf_counter()
    val = validation_loss(
        run.model,
        val_ds,
        run.val_loss_fn,
        run.device,
        num_workers=run.cfg["num_workers"],
        amp_dtype=run.amp_dtype,
    )
    val_seconds = time.perf_counter() - tv
    lr = run.opt.param_groups[0]["lr"]
    run.sched.step(val)
    row = {
        "epoch": state.epoch,
        "train_loss": state.loss_sum / max(state.loss_count, 1),
        "val_loss": val,
        "lr": lr,
        "seconds": state.train_seconds + val_seconds,
        "images_per_s": state.loss_count / max(state.train_seconds, 1e-9),
    }
    log.info(
        "epoch %d: train %.5f val %.5f lr %.2e (%.1f s, %.0f img/s)",
        state.epoch,
        row["train_loss"],
        val,
        lr,
        row["seconds"],
        row["images_per_s"],
    )
    return row


def _keep_best(run: _Run, val: float) -> None:
    """Early-stopping bookkeeping; the weights of a validation loss below the best so
    far are saved to ``best.pt`` (a gain under ``min_delta`` still counts as stagnant)."""
    state = run.state
    better = val < state.best_val
    if val < state.best_val - run.cfg["min_delta"]:
        state.bad_epochs = 0
    else:
        state.bad_epochs += 1
    if better:
        state.best_val = val
        if run.ranks.main:
            best = {"model": run.model.state_dict(), "epoch": state.epoch, "val_loss": val}
            atomic_save(best, run.best_path)


def _end_epoch(run: _Run, val_ds) -> None:
    """Validate, step the scheduler, keep the best weights, decide on stopping and
    checkpoint."""
    cfg, state = run.cfg, run.state
    row = _validate(run, val_ds)
    state.history.append(row)
    _keep_best(run, row["val_loss"])
    state.epoch += 1
    state.batch_in_epoch, state.loss_sum, state.loss_count, state.train_seconds = 0, 0.0, 0, 0.0
    if state.bad_epochs >= cfg["early_stop_patience"]:
        state.stop("early_stop")
    elif state.epoch >= cfg["max_epochs"]:
        state.stop("max_epochs")
    run.checkpoint()
    if run.ranks.main:
        write_log(state.history, run.setup.out_dir / "training_log.csv")


def _train(setup: TrainingSetup, train_shards, val_shards) -> dict[str, Any]:
    """The loop: epochs until early stopping or ``max_epochs`` (or ``max_steps``), then
    ``model.pt`` from the best weights."""
    cfg = setup.cfg
    run = _start(setup, train_shards)
    _resume(run)
    state = run.state
    train_ds = _training_batches(setup, train_shards)
    val_ds = ShardBatches(
        val_shards,
        cfg["val_batch_size"] or cfg["batch_size"],
        setup.whitening,
        shuffle=False,
        pixel_scale=cfg["pixel_scale"],
        mask_factor=cfg["mask_factor"],
        inputs=setup.inputs,
    )
    max_steps = cfg["max_steps"]
    if max_steps is not None and state.step >= max_steps and not state.finished:
        return summary(state, None, finished=False)
    run.model.train()
    while not state.finished:
        if state.epoch >= cfg["max_epochs"]:
            state.stop("max_epochs")
            break
        if _train_epoch(run, train_ds, max_steps):
            return summary(state, None, finished=False)
        _end_epoch(run, val_ds)
    run.checkpoint()
    model_path = setup.out_dir / "model.pt"
    if run.ranks.main:
        write_model(run, setup.whitening, setup.inputs, setup.out_dir)
        write_log(state.history, setup.out_dir / "training_log.csv")
    run.ranks.barrier()
    return summary(state, model_path, finished=True)


def _training_batches(setup: TrainingSetup, train_shards):
    """The training set: a copy of the stream with the run's whitening, inputs and
    pre-processing, or the shards shuffled per epoch; this rank's part of it."""
    cfg = setup.cfg
    if isinstance(train_shards, StreamBatches):
        if train_shards.batch_size != cfg["batch_size"]:
            raise ValueError(
                f"the training stream has batches of {train_shards.batch_size} images, "
                f"training.batch_size is {cfg['batch_size']}"
            )
        ds = copy.copy(train_shards)
        ds.whitening, ds.inputs = setup.whitening, setup.inputs
        ds.pixel_scale, ds.mask_factor = cfg["pixel_scale"], cfg["mask_factor"]
    else:
        ds = ShardBatches(
            train_shards,
            cfg["batch_size"],
            setup.whitening,
            shuffle=True,
            seed=int(cfg["seed"]),
            block_size=cfg["block_size"],
            window=cfg["shuffle_window"],
            drop_last=True,
            pixel_scale=cfg["pixel_scale"],
            mask_factor=cfg["mask_factor"],
            inputs=setup.inputs,
        )
    if setup.ranks.size > 1:
        ds.part = (setup.ranks.rank, setup.ranks.size)
    if len(ds) == 0:
        raise ValueError(
            f"training shards hold {ds.n_images} images, fewer than one batch of "
            f"{cfg['batch_size']}"
        )
    return ds
