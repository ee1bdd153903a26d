"""What a training run of the ratio estimator is given (:class:`TrainingSetup`), where it
stands (:class:`TrainingState`, saved whole in each checkpoint) and torch's determinism
switches for its duration (:func:`deterministic_torch`); the loop is
:mod:`subslope.nre.train`."""

from __future__ import annotations

import math
import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import torch

from .distributed import Ranks
from .inputs import InputTransform

__all__ = ["TrainingSetup", "TrainingState", "deterministic_torch"]


@contextmanager
def deterministic_torch(cfg: Mapping[str, Any], device: torch.device) -> Iterator[None]:
    """torch's deterministic algorithms (``deterministic: true``) or cuDNN's autotuner on
    CUDA, for the duration of the run; the previous settings restored after it."""
    prev_det = torch.are_deterministic_algorithms_enabled()
    prev_bench = torch.backends.cudnn.benchmark
    if cfg["deterministic"]:
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True)
        torch.backends.cudnn.benchmark = False
    elif device.type == "cuda":
        torch.backends.cudnn.benchmark = True
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(prev_det)
        torch.backends.cudnn.benchmark = prev_bench


@dataclass(frozen=True)
class TrainingSetup:
    """What a training run is given: its config, devices, data transforms and folders."""

    cfg: dict[str, Any]
    chash: str
    device: torch.device
    ranks: Ranks
    amp_dtype: torch.dtype | None
    whitening: tuple[float, float]
    inputs: InputTransform
    out_dir: Path
    ckpt_dir: Path

    @property
    def last_path(self) -> Path:
        return self.ckpt_dir / "last.pt"

    @property
    def best_path(self) -> Path:
        return self.ckpt_dir / "best.pt"


@dataclass
class TrainingState:
    """Where a training run stands; saved whole in ``last.pt`` (as a mapping)."""

    epoch: int = 0
    batch_in_epoch: int = 0
    step: int = 0
    best_val: float = math.inf
    bad_epochs: int = 0
    history: list[dict[str, Any]] = field(default_factory=list)
    loss_sum: float = 0.0
    loss_count: int = 0
    train_seconds: float = 0.0
    finished: bool = False
    stop_reason: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, saved: Mapping[str, Any]) -> TrainingState:
        """The state of a checkpoint's mapping (keys it lacks keep their start values)."""
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in saved.items() if k in known})

    def stop(self, reason: str) -> None:
        self.finished, self.stop_reason = True, reason
