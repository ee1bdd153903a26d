"""Streaming, reproducibly shuffled training batches from HDF5 shards.

Shard layout read here (written by :mod:`subslope.io.shards`): ``images`` ``(N, H, W)``
float32 e⁻/s per pixel; ``params/gamma_sub``, ``params/theta_e``, ``params/lens_x``,
``params/lens_y`` ``(N,)``; root attribute ``complete = True``.

Nothing is loaded up front but the shard lengths: at paper scale (5·10⁶ images,
~200 GB) each batch is read from disk when it is asked for.

Order of an epoch
-----------------
The rows of all shards are cut into *blocks* of ``block_size`` consecutive rows (the
last block of a shard may be shorter). For epoch ``e`` the blocks are permuted with
``numpy.random.default_rng([seed, e])`` and concatenated into one sequence of rows,
which is cut into consecutive batches of ``batch_size``. With ``window > 1`` the rows
of every ``window`` consecutive batches are also shuffled among themselves (generator
``[seed, e, window index]``) before cutting. Rows of a simulation shard are independent
draws from the prior, so shuffling blocks already gives batches that are independent
samples; the window adds mixing across blocks at the price of reading up to ``window``
times more rows (each batch reads, for every block it touches, the span of rows it needs).

The order is a pure function of ``(seed, epoch)`` and of the shard list: it does not
depend on the number of workers. Each batch is an item of a map-style dataset
(``dataset[b]`` is batch ``b`` of the current epoch), so a ``DataLoader`` with any
``num_workers`` returns the batches in index order, every row exactly once per epoch
(the last batch is partial unless ``drop_last``), and a run resumed mid-epoch continues
from batch ``b`` with :func:`make_loader` ``(start=b)``.

Workers
-------
HDF5 handles are opened lazily in the process that reads, and never inherited: a
dataset copied into a forked worker notices the new process id and opens its own
handles (the handles of the parent are left alone), and pickling drops them.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import h5py
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from subslope.io.shards import CheckedRows, open_hdf5
from subslope.physics.instrument import PIXEL_SCALE
from subslope.ragged import counts_to_offsets

from .inputs import InputTransform, read_light_fit, shard_light_models
from .preprocess import preprocess, read_whitening

__all__ = ["ShardBatches", "batch_tensors", "make_loader", "read_labels", "shard_lengths"]

PARAM_KEYS = ("gamma_sub", "theta_e", "lens_x", "lens_y")


def _check_shard(path, fh: h5py.File, *, require_label: bool = True) -> int:
    if not bool(fh.attrs.get("complete", False)):
        raise ValueError(
            f"shard {os.fspath(path)!r} is not marked complete (root attribute 'complete' is not "
            "True)"
        )
    if "images" not in fh:
        raise ValueError(f"shard {os.fspath(path)!r} has no 'images' dataset")
    n = fh["images"].shape[0]
    for key in PARAM_KEYS:
        if key == "gamma_sub" and not require_label and "params/gamma_sub" not in fh:
            continue
        if f"params/{key}" not in fh:
            raise ValueError(f"shard {os.fspath(path)!r} has no 'params/{key}' dataset")
        if fh[f"params/{key}"].shape != (n,):
            raise ValueError(
                f"shard {os.fspath(path)!r}: params/{key} has shape {fh[f'params/{key}'].shape}, "
                f"expected ({n},)"
            )
    return n


def shard_lengths(paths: Sequence, *, require_label: bool = True) -> list[int]:
    """Number of images in each shard (checks the layout and the ``complete`` flag)."""
    out = []
    for p in paths:
        with open_hdf5(p) as fh:
            out.append(_check_shard(p, fh, require_label=require_label))
    return out


def read_labels(paths: Sequence, key: str = "gamma_sub") -> np.ndarray:
    """All values of ``params/<key>`` of the shards, concatenated (float64)."""
    vals = []
    for p in paths:
        with open_hdf5(p) as fh:
            _check_shard(p, fh)
            vals.append(np.asarray(CheckedRows(p, fh[f"params/{key}"])[...], dtype=np.float64))
    return np.concatenate(vals) if vals else np.zeros(0)


class ShardBatches(Dataset):
    """Batches of pre-processed images and their parameters, read from HDF5 shards.

    ``dataset[b]`` is a dict of tensors: ``x`` ``(n, 1, H, W)`` float32 (whitened and
    masked with :func:`~subslope.nre.preprocess.preprocess` when ``whitening`` is given,
    raw e⁻/s otherwise), ``gamma``, ``theta_e``, ``lens_x``, ``lens_y`` ``(n,)`` float32,
    and ``index`` ``(n,)`` int64, the global row number (shards concatenated in order).
    Shards without ``params/gamma_sub`` (e.g. the NFW/tNFW test sets) are accepted with
    ``require_label=False`` and give ``gamma = NaN``.

    Parameters
    ----------
    paths: shard files.
    batch_size: images per batch.
    whitening: ``(mean, std)``, a mapping, a JSON path, or ``None`` for raw images.
    shuffle: permute blocks per epoch (validation/inference: ``False``, file order).
    seed: base of the per-epoch shuffling.
    block_size: rows read contiguously.
    window: number of batches whose rows are shuffled together (1: blocks only).
    drop_last: drop the last, partial batch of an epoch.
    pixel_scale, mask_factor: passed to ``preprocess``.
    require_label: demand ``params/gamma_sub`` in every shard.
    inputs: the input transform applied before whitening (:mod:`subslope.nre.inputs`;
        ``None``: the pixels as stored).
    """

    def __init__(
        self,
        paths: Sequence,
        batch_size: int,
        whitening=None,
        *,
        shuffle: bool = True,
        seed: int = 0,
        block_size: int = 128,
        window: int = 1,
        drop_last: bool = False,
        pixel_scale: float = PIXEL_SCALE,
        mask_factor: float | None = 1.5,
        require_label: bool = True,
        inputs: InputTransform | None = None,
    ):
        if not paths:
            raise ValueError("paths: need at least one shard")
        for name, v in (("batch_size", batch_size), ("block_size", block_size), ("window", window)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        self.paths = [os.fspath(p) for p in paths]
        self.batch_size, self.block_size, self.window = (
            int(batch_size),
            int(block_size),
            int(window),
        )
        self.whitening = None if whitening is None else read_whitening(whitening)
        self.shuffle, self.seed, self.drop_last = bool(shuffle), int(seed), bool(drop_last)
        self.pixel_scale, self.mask_factor = pixel_scale, mask_factor
        self.inputs = inputs or InputTransform()
        self.lengths = shard_lengths(self.paths, require_label=require_label)
        if self.inputs.needs_light:
            for p in self.paths:
                with open_hdf5(p) as fh:
                    read_light_fit(p, fh, 0, 0)
        self.offsets = counts_to_offsets(np.asarray(self.lengths))
        self.n_images = int(self.offsets[-1])
        if self.n_images == 0:
            raise ValueError(f"shards {self.paths} hold no images")
        shard_ids, starts, lens = [], [], []
        for s, n in enumerate(self.lengths):
            for a in range(0, n, self.block_size):
                shard_ids.append(s)
                starts.append(a)
                lens.append(min(self.block_size, n - a))
        self._block_shard = np.asarray(shard_ids, dtype=np.int64)
        self._block_start = np.asarray(starts, dtype=np.int64)
        self._block_len = np.asarray(lens, dtype=np.int64)
        self.epoch = 0
        self.part: tuple[int, int] | None = None  # (rank, ranks): read that share only
        self._plan: tuple[int, np.ndarray, np.ndarray] | None = None
        self._files: dict[int, h5py.File] = {}
        self._pid = os.getpid()

    # -- order ------------------------------------------------------------------------
    def set_epoch(self, epoch: int) -> None:
        """Select the shuffling of epoch ``epoch`` (call before building the loader)."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        if self.drop_last:
            return self.n_images // self.batch_size
        return math.ceil(self.n_images / self.batch_size)

    def _epoch_plan(self) -> tuple[np.ndarray, np.ndarray]:
        if self._plan is None or self._plan[0] != self.epoch:
            nb = len(self._block_len)
            order = (
                np.random.default_rng([self.seed, self.epoch]).permutation(nb)
                if self.shuffle
                else np.arange(nb)
            )
            ends = np.cumsum(self._block_len[order])
            self._plan = (self.epoch, order, ends)
        return self._plan[1], self._plan[2]

    def batch_rows(self, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(block, shard, row)`` of each image of batch ``b`` of the current epoch, in batch
        order."""
        if not 0 <= b < len(self):
            raise IndexError(f"batch index {b} out of range for {len(self)} batches")
        order, ends = self._epoch_plan()
        w = b // self.window if self.shuffle else b
        span = self.batch_size * (self.window if self.shuffle else 1)
        pos = np.arange(w * span, min((w + 1) * span, self.n_images), dtype=np.int64)
        if self.shuffle and self.window > 1:
            pos = np.random.default_rng([self.seed, self.epoch, w]).permutation(pos)
        k = b - w * (self.window if self.shuffle else 1)
        pos = pos[k * self.batch_size : (k + 1) * self.batch_size]
        slot = np.searchsorted(ends, pos, side="right")
        blk = order[slot]
        start_pos = ends[slot] - self._block_len[blk]
        rows = self._block_start[blk] + (pos - start_pos)
        return blk, self._block_shard[blk], rows

    # -- reading ----------------------------------------------------------------------
    def _file(self, s: int) -> h5py.File:
        if os.getpid() != self._pid:  # forked copy: never use the parent's handles
            self._files, self._pid = {}, os.getpid()
        fh = self._files.get(s)
        if fh is None:
            fh = self._files[s] = open_hdf5(self.paths[s])
        return fh

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_files"] = {}
        return state

    def close(self) -> None:
        if os.getpid() == self._pid:
            for fh in self._files.values():
                fh.close()
        self._files = {}

    def __getitem__(self, b: int) -> dict[str, torch.Tensor]:
        blk, shard, rows = self.batch_rows(int(b))
        if self.part is not None:  # data-parallel training: this rank's contiguous share
            rank, ranks = self.part
            lo, hi = rank * len(rows) // ranks, (rank + 1) * len(rows) // ranks
            blk, shard, rows = blk[lo:hi], shard[lo:hi], rows[lo:hi]
        n = len(rows)
        images = light = None
        params = {k: np.empty(n, dtype=np.float32) for k in PARAM_KEYS}
        for bk in np.unique(blk):  # one contiguous read per block touched
            sel = np.flatnonzero(blk == bk)
            s = int(self._block_shard[bk])
            lo, hi = int(rows[sel].min()), int(rows[sel].max()) + 1
            fh = self._file(s)
            chunk = CheckedRows(self.paths[s], fh["images"])[lo:hi]
            if images is None:
                images = np.empty((n, *chunk.shape[1:]), dtype=np.float32)
            images[sel] = chunk[rows[sel] - lo]
            if self.inputs.needs_light:
                light = np.empty_like(images) if light is None else light
                light[sel] = shard_light_models(self.paths[s], fh, lo, hi, rows[sel] - lo)
            for k in PARAM_KEYS:
                if f"params/{k}" in fh:
                    rows_k = CheckedRows(self.paths[s], fh[f"params/{k}"])[lo:hi]
                    params[k][sel] = rows_k[rows[sel] - lo]
                else:  # unlabelled shard (require_label=False)
                    params[k][sel] = np.nan
        return batch_tensors(
            self.inputs.apply(images, light),
            params,
            self.offsets[shard] + rows,
            self.whitening,
            pixel_scale=self.pixel_scale,
            mask_factor=self.mask_factor,
        )


def batch_tensors(
    images: np.ndarray,
    params,
    index: np.ndarray,
    whitening=None,
    *,
    pixel_scale: float = PIXEL_SCALE,
    mask_factor: float | None = 1.5,
) -> dict[str, torch.Tensor]:
    """One training batch as the estimator takes it, from images ``(n, H, W)`` (e⁻/s) and
    float32 ``params`` (``gamma_sub``, ``theta_e``, ``lens_x``, ``lens_y``): ``x`` ``(n, 1, H,
    W)`` pre-processed with :func:`~subslope.nre.preprocess.preprocess` when ``whitening``
    (mean, std) is given, the parameters as ``gamma``, ``theta_e``, ``lens_x``, ``lens_y``
    and ``index`` (int64, the images' numbers)."""
    x = torch.from_numpy(np.ascontiguousarray(images, dtype=np.float32))
    p = {k: torch.from_numpy(np.ascontiguousarray(params[k], dtype=np.float32)) for k in PARAM_KEYS}
    if whitening is not None:
        x = preprocess(
            x,
            p["theta_e"],
            p["lens_x"],
            p["lens_y"],
            *whitening,
            pixel_scale=pixel_scale,
            mask_factor=mask_factor,
        )
    out = {"x": x.unsqueeze(1), "gamma": p["gamma_sub"]}
    for k in ("theta_e", "lens_x", "lens_y"):
        out[k] = p[k]
    out["index"] = torch.from_numpy(np.asarray(index, dtype=np.int64))
    return out


def _worker_init(_worker_id: int) -> None:
    # Workers only read and pre-process; one intra-op thread each avoids oversubscription.
    torch.set_num_threads(1)


def make_loader(
    dataset: Dataset,
    *,
    start: int = 0,
    num_workers: int = 0,
    pin_memory: bool = False,
    prefetch_factor: int | None = None,
) -> DataLoader:
    """A ``DataLoader`` over batches ``start, start+1, …`` of the dataset's current epoch.

    ``dataset``: a :class:`ShardBatches` or a :class:`subslope.nre.stream.StreamBatches`
    (anything with ``seed``, ``epoch`` and one batch per item; its optional
    ``multiprocessing_context`` is the workers' start method). The loader gets its own
    ``torch.Generator`` (seeded from the dataset's seed and epoch): creating an iterator
    then draws nothing from the global torch RNG, so a training run resumed from a
    checkpoint sees the same global random stream as an uninterrupted one.
    """
    gen = torch.Generator().manual_seed(
        int(np.random.SeedSequence([dataset.seed, dataset.epoch]).generate_state(1)[0])
    )
    kwargs = {"generator": gen}
    if num_workers > 0:
        kwargs.update(
            worker_init_fn=_worker_init,
            prefetch_factor=prefetch_factor or 2,
            multiprocessing_context=getattr(dataset, "multiprocessing_context", None),
        )
    return DataLoader(
        dataset,
        batch_size=None,
        shuffle=False,
        sampler=range(int(start), len(dataset)),
        num_workers=num_workers,
        pin_memory=pin_memory,
        **kwargs,
    )
