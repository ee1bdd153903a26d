"""Training batches simulated while training runs: a live stream from the scene's priors in
place of training shards (``training.data: stream``).

Batch ``b`` of epoch ``e`` is simulated from ``numpy.random.SeedSequence(entropy=seed,
spawn_key=(e, b))``. It is a pure function of ``(seed, epoch, batch)``:

- the stream is the same for any number of ``DataLoader`` workers (each worker simulates
  the batches the loader hands it; the loader returns them in batch order);
- a run resumed mid-epoch continues with the images the interrupted one would have seen;
- every epoch sees images never seen before, so the estimator cannot memorise them.

Nothing is written to disk. Validation stays on fixed shards, so the early-stopping
criterion compares epochs on the same images. The simulator is an object with two methods,
passed in by the caller (:class:`subslope.stages.train.SceneStream` simulates a
scene of the campaign), so that this module needs nothing of the simulation:

``images(n, seed_sequence) -> (images (n, H, W) float32 e⁻/s, params)``
    ``params`` holds at least ``gamma_sub``, ``theta_e``, ``lens_x``, ``lens_y`` ``(n,)``,
    and ``light_model`` ``(n, H, W)`` (the fitted lens light) where the input transform
    (``inputs``, set by the training run) subtracts it;
``labels(n, seed_sequence) -> (n,)``
    labels γ drawn from the same prior (cheap: no images), for the γ normalisation.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import Dataset

from subslope.physics.instrument import PIXEL_SCALE

from .data import batch_tensors
from .inputs import InputTransform
from .preprocess import read_whitening

__all__ = ["StreamBatches", "LABEL_SAMPLE"]

#: Labels drawn for the γ normalisation of a streamed run.
LABEL_SAMPLE = 10_000


class StreamBatches(Dataset):
    """``n_batches`` batches of ``batch_size`` freshly simulated images per epoch.

    ``dataset[b]`` is the dict of :func:`subslope.nre.data.batch_tensors`; ``index`` numbers
    the images of the epoch (``b * batch_size + k``). ``multiprocessing_context``:
    the workers' start method (``"spawn"`` when the simulator renders on CUDA, which a
    forked process cannot use; ``None``: the platform's default).
    """

    def __init__(
        self,
        simulator,
        batch_size: int,
        n_batches: int,
        whitening=None,
        *,
        seed: int = 0,
        pixel_scale: float = PIXEL_SCALE,
        mask_factor: float | None = 1.5,
        multiprocessing_context: str | None = None,
    ):
        for name, v in (("batch_size", batch_size), ("n_batches", n_batches)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        self.simulator = simulator
        self.batch_size, self.n_batches = int(batch_size), int(n_batches)
        self.whitening = None if whitening is None else read_whitening(whitening)
        self.inputs = InputTransform()
        self.seed = int(seed)
        self.pixel_scale, self.mask_factor = pixel_scale, mask_factor
        self.multiprocessing_context = multiprocessing_context
        self.epoch = 0
        self.part: tuple[int, int] | None = None  # (rank, ranks): simulate that share only

    @property
    def n_images(self) -> int:
        """Images per epoch."""
        return self.batch_size * self.n_batches

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return self.n_batches

    def seed_sequence(self, b: int) -> np.random.SeedSequence:
        """The seeds of batch ``b`` of the current epoch."""
        return np.random.SeedSequence(entropy=self.seed, spawn_key=(self.epoch, int(b)))

    def labels(self, n: int = LABEL_SAMPLE) -> np.ndarray:
        """``n`` labels γ from the stream's prior (a stream of their own, not a batch's)."""
        seq = np.random.SeedSequence(entropy=self.seed, spawn_key=(2**32 - 1,))
        return np.asarray(self.simulator.labels(int(n), seq), dtype=np.float64)

    def __getitem__(self, b: int) -> dict[str, torch.Tensor]:
        if not 0 <= int(b) < len(self):
            raise IndexError(f"batch index {b} out of range for {len(self)} batches")
        seq, n, first = self.seed_sequence(b), self.batch_size, 0
        if self.part is not None:  # data-parallel training: this rank's share, own seeds
            rank, ranks = self.part
            first, n = rank * n // ranks, (rank + 1) * n // ranks - rank * n // ranks
            seq = np.random.SeedSequence(entropy=self.seed, spawn_key=(self.epoch, int(b), rank))
        images, params = self.simulator.images(n, seq)
        index = int(b) * self.batch_size + first + np.arange(n)
        light = params.get("light_model") if self.inputs.needs_light else None
        if self.inputs.needs_light and light is None:
            raise ValueError(
                "inputs 'light_subtracted': the stream's simulator gives no 'light_model' "
                "(simulation.light_fit must be on)"
            )
        return batch_tensors(
            self.inputs.apply(images, light),
            params,
            index,
            self.whitening,
            pixel_scale=self.pixel_scale,
            mask_factor=self.mask_factor,
        )
