"""Stage ``train``: the estimator's training section from the config, the checkpoint
key and the training run (rule train_estimator)."""

from __future__ import annotations

import copy
import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from subslope.config import STREAMED_SCENE, light_fit_enabled
from subslope.nre.training_config import WORKFLOW_KEYS, config_hash, resolve_config
from subslope.plan import derived_seed

__all__ = [
    "training_section",
    "input_transform",
    "checkpoint_key",
    "data_fingerprint",
    "SceneStream",
    "training_stream",
    "run_training",
    "train_job",
]


def training_section(config: Mapping[str, Any]) -> dict[str, Any]:
    """The ``subslope.nre.train`` config from the workflow config (validated, defaults filled).

    ``seed: null`` becomes a seed derived from the global seed; ``arch`` keys that are
    null take the preset's value; the pixel scale comes from ``instrument``; workflow-only
    keys (device, threads, gpus, mem_mb, runtime) are dropped; no progress bar.
    """
    tr = copy.deepcopy(dict(config["training"]))
    for key in WORKFLOW_KEYS:
        tr.pop(key, None)
    tr["arch"] = {k: v for k, v in dict(tr.get("arch") or {}).items() if v is not None}
    if tr.get("seed") is None:
        tr["seed"] = derived_seed(config["seed"], "training")
    tr["pixel_scale"] = float(config["instrument"]["pixel_scale"])
    tr["progress"] = False
    return tr


def _launch_ranks(training, train_shards, val_shards, whitening, out_dir, ckpt_dir, device,
                  stream, ranks: int) -> dict[str, Any]:  # fmt: skip
    """:func:`run_training` as ``ranks`` torchrun processes; the summary from ``model.pt``."""
    from subslope.devices import pick_device
    from subslope.nre.checkpoints import load_estimator
    from subslope.nre.distributed import launch

    job = {
        "training": dict(training), "train_shards": [os.fspath(p) for p in train_shards],
        "val_shards": [os.fspath(p) for p in val_shards], "whitening": os.fspath(whitening),
        "out_dir": os.fspath(out_dir), "ckpt_dir": os.fspath(ckpt_dir),
        "device": device or "auto", "stream": stream,
    }  # fmt: skip
    launch(job, ranks, module=__name__, device_type=pick_device(device).type)
    model_path = Path(out_dir) / "model.pt"
    _, meta = load_estimator(model_path)
    return {"finished": True, "model": model_path, "ranks": ranks,
            "best_val_loss": meta["best_val_loss"], "stop_reason": meta["stop_reason"]}  # fmt: skip


def input_transform(config: Mapping[str, Any]):
    """The estimator's input transform of a workflow config (``training.inputs`` with the
    detector's empty-pixel σ_bg and total exposure time,
    :class:`subslope.nre.inputs.InputTransform`)."""
    from subslope.nre.inputs import InputTransform
    from subslope.simulation.observing import build_instrument

    inst = build_instrument(config)
    return InputTransform(
        config["training"]["inputs"], inst.background_sigma, inst.total_exposure_time
    )


def checkpoint_key(
    training: Mapping[str, Any],
    train_shards: Sequence,
    val_shards: Sequence,
    data_hashes: Mapping[str, str] | None = None,
) -> str:
    """12 hex digits naming the checkpoint folder of one training run.

    Depends on the training section (without the resume-safe keys) and on the data
    (shard paths and the simulation hashes of their scenes), so a restarted job with the
    same inputs resumes while a changed config or data starts a fresh folder.
    """
    payload = {
        "training": config_hash(resolve_config(training)),
        "train": [os.fspath(p) for p in train_shards],
        "val": [os.fspath(p) for p in val_shards],
        "data": dict(data_hashes or {}),
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:12]


def data_fingerprint(
    train_shards: Sequence, val_shards: Sequence, whitening, stream: Mapping | None = None
) -> str:
    """12 hex digits of the SHA-256 of every training and validation shard's bytes, of
    the whitening JSON and of the streamed scene's simulation sections (``stream``: the
    runnable config of a streamed run, :func:`training_stream`). Refuses a whitening file
    whose recorded shard checksums are not those of ``train_shards`` now (it was computed
    from other images); a shard that changed because it is corrupt is named as such
    (:func:`subslope.io.shards.verify_shard`)."""
    from subslope.io.atomic import read_json
    from subslope.io.shards import file_sha256, verify_shard

    sums = {os.fspath(p): file_sha256(p) for p in [*train_shards, *val_shards]}
    if isinstance(whitening, (str, os.PathLike)):
        recorded = read_json(whitening).get("shards") or []
        stale = [
            r["path"]
            for r in recorded
            if r.get("path") in sums and r.get("sha256") not in (None, sums[r["path"]])
        ]
        for path in stale:  # a corrupt shard is named as such, not as a stale whitening
            verify_shard(path)
        if stale:
            raise ValueError(
                f"whitening file {os.fspath(whitening)} was computed from other contents of "
                f"{stale}; rerun its rule (snakemake -R compute_whitening) before training"
            )
        sums["whitening"] = file_sha256(whitening)
    if stream is not None:
        from subslope.config import config_hash as sections_hash
        from subslope.simulation.resolve import simulation_sections

        sums["stream"] = sections_hash(simulation_sections(stream, STREAMED_SCENE))
    return hashlib.sha256(json.dumps(sums, sort_keys=True).encode()).hexdigest()[:12]


class SceneStream:
    """The simulator of a streamed training run (:mod:`subslope.nre.stream`): images of
    ``scene`` exactly as its shards would hold them, from the runnable config ``config``
    (:func:`subslope.stages.simulate.runnable_config`). Picklable, so that data-loader
    workers (forked or spawned) each simulate their own batches."""

    def __init__(self, config: Mapping[str, Any], scene: str = STREAMED_SCENE):
        self.config, self.scene = copy.deepcopy(dict(config)), scene

    def images(self, n: int, seed_sequence):
        """``n`` noisy images and their parameters, as
        ``subslope.simulation.shard.simulate_images`` gives them."""
        from subslope.simulation.shard import simulate_images

        out = simulate_images(self.config, self.scene, n, seed_sequence)
        params = out["params"]
        if light_fit_enabled(self.config):
            from subslope.simulation.observing import fitted_light_models

            _, light = fitted_light_models(
                self.config, out["images"], params["theta_e"], out["psf"]
            )
            params = {**params, "light_model": light}
        return out["images"], params

    def labels(self, n: int, seed_sequence):
        """``n`` labels γ from the scene's macro prior (no images)."""
        import numpy as np

        from subslope.simulation.macro import sample_macro
        from subslope.simulation.resolve import resolved_scene

        scene, _ = resolved_scene(self.config, self.scene)
        return sample_macro(scene, n, np.random.default_rng(seed_sequence))["gamma_sub"]


def training_stream(training: Mapping[str, Any], stream: Mapping[str, Any]):
    """The :class:`subslope.nre.stream.StreamBatches` of a streamed run: an epoch of the
    streamed scene's ``n_shards × images_per_shard`` images (whole batches), seeded by the
    training seed; workers start by ``spawn`` when the images are rendered on CUDA."""
    from subslope.devices import pick_device
    from subslope.nre.stream import StreamBatches

    cfg = resolve_config(training)
    counts = stream["simulation"]["scenes"][STREAMED_SCENE]
    n_batches = int(counts["n_shards"]) * int(counts["images_per_shard"]) // cfg["batch_size"]
    if n_batches < 1:
        raise ValueError(
            f"simulation.scenes.{STREAMED_SCENE} holds fewer images than one batch of "
            f"training.batch_size = {cfg['batch_size']}"
        )
    render_device = pick_device(
        stream["simulation"]["render"].get("device", "auto"), key="simulation.render.device"
    )
    return StreamBatches(
        SceneStream(stream),
        cfg["batch_size"],
        n_batches,
        seed=int(cfg["seed"]),
        pixel_scale=cfg["pixel_scale"],
        mask_factor=cfg["mask_factor"],
        multiprocessing_context="spawn" if render_device.type == "cuda" else None,
    )


def run_training(
    training: Mapping[str, Any],
    train_shards: Sequence,
    val_shards: Sequence,
    whitening,
    out_dir,
    ckpt_dir,
    *,
    device: str = "auto",
    stream: Mapping[str, Any] | None = None,
    ranks: int = 1,
) -> dict[str, Any]:
    """Train (resuming from ``ckpt_dir`` when possible); ``out_dir`` gets model.pt +
    training_log.csv. ``stream``: the runnable config of the streamed scene
    (``training.data: stream``; ``train_shards`` is then empty) — the training images are
    simulated while training (:func:`training_stream`). ``ranks`` > 1: as that many
    data-parallel processes started by torchrun (:mod:`subslope.nre.distributed`), each
    running this function.

    The checkpoints live in ``ckpt_dir/data-<fingerprint>`` (:func:`data_fingerprint`):
    shards whose content changed under the same paths and config start a fresh run
    instead of resuming one trained on other images."""
    from subslope.nre.train import train

    dev = None if device in (None, "auto") else device
    key = data_fingerprint(train_shards, val_shards, whitening, stream)
    ckpt = Path(ckpt_dir) / f"data-{key}"
    if ranks > 1 and "WORLD_SIZE" not in os.environ:  # start the ranks; each runs this
        return _launch_ranks(
            training, train_shards, val_shards, whitening, out_dir, ckpt_dir, dev, stream, ranks
        )
    data = training_stream(training, stream) if stream is not None else list(train_shards)
    summary = train(training, data, list(val_shards), whitening, out_dir, ckpt, device=dev)
    if not summary["finished"]:
        raise RuntimeError(
            f"training stopped before the end ({summary}); run again to resume from {ckpt_dir}"
        )
    return summary


def train_job(
    run: Mapping[str, Any],
    *,
    training: Mapping[str, Any],
    train_shards: Sequence,
    val_shards: Sequence,
    whitening,
    model_path,
    ckpt_dir,
    device: str,
    stream: Mapping[str, Any] | None,
    stream_data: Sequence = (),
    threads: int | None = None,
) -> dict[str, Any]:
    """The workflow's training job (rule train_estimator): ``training``, ``ckpt_dir``,
    ``device`` and ``stream`` are the rule's params (:func:`training_section`, the
    checkpoint folder, ``training.device``, the streamed scene's resolved config or None),
    ``run`` the workflow's config (its ``training.ranks``: processes, not a param since
    their number does not change the training); ``stream_data``: the files a stream
    simulates from, checked first; ``threads``: torch's CPU threads. A device this machine
    lacks fails before anything runs."""
    import logging

    import torch

    from subslope.devices import pick_device
    from subslope.io.resources import verify_files
    from subslope.plan import runnable_config

    pick_device(device, key="training.device")
    if threads is not None:
        torch.set_num_threads(int(threads))
    log = logging.getLogger(__name__)
    log.info("checkpoints in %s (kept across reruns; a restarted job resumes)", ckpt_dir)
    if stream is not None:  # training.data: stream
        verify_files(list(stream_data))
        stream = runnable_config(stream, run)
    summary = run_training(
        training,
        list(train_shards),
        list(val_shards),
        whitening,
        os.path.dirname(model_path),
        ckpt_dir,
        device=device,
        stream=stream,
        ranks=run["training"]["ranks"],
    )
    log.info("training done: %s", summary)
    return summary


if __name__ == "__main__":  # one rank of a data-parallel training (torchrun)
    import sys

    run_training(**json.loads(sys.argv[1]))
