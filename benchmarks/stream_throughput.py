"""Training images/s from shards against training from the live simulator stream
(``training.data: stream``), on this machine.

The train scene of ``--config`` (the reduced campaign: N_sub ~ U{0, 3000} + LoS, mean 1500)
feeds the reduced estimator, batches of ``--batch`` images, one optimiser step per batch:

- ``shards``: ``--batches`` batches read from a shard simulated beforehand (not timed), as
  the campaign trains by default (``ShardBatches``, whitened and masked);
- ``stream, W workers``: the same number of batches simulated by ``W`` data-loader
  workers while the training process steps (``subslope.stages.train.training_stream``);
- ``stream only, W workers``: the loader alone, without the optimiser step.

Each row: the median over ``--repeats`` runs of images/s, timed from the second batch on
(the first carries worker start-up and kernel compilation; the start-up is shown apart).

    OMP_NUM_THREADS=1 SUBSLOPE_DATA_MIRROR=../shared/data \\
        .venv/bin/python benchmarks/stream_throughput.py [--batch 32] [--batches 6]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine_info  # noqa: E402

from subslope import config as C  # noqa: E402
from subslope.devices import pick_device  # noqa: E402
from subslope.nre import NRELoss, ShardBatches, build_model, make_loader  # noqa: E402
from subslope.plan import shard_job_config  # noqa: E402
from subslope.simulation.shard import simulate_shard  # noqa: E402
from subslope.stages.simulate import runnable_config  # noqa: E402
from subslope.stages.train import training_section, training_stream  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
WHITENING = (0.05, 0.3)


def _config(args) -> dict:
    over = {
        "data": {"resources_dir": str(args.data)},
        "training": {"batch_size": args.batch, "data": "stream"},
        "domain": {"scene": "validation"},
        "simulation": {
            "scenes": {"train": {"n_shards": 1, "images_per_shard": args.batch * args.batches}},
            "shard_cache": None,
        },
    }
    if args.batch_images is not None:
        over["simulation"]["render"] = {"batch_images": args.batch_images}
    return C.load(args.config, overrides=over, env=False)


def _run(loader, step) -> tuple[float, float]:
    """(start-up s: until the first batch is stepped, images/s over the rest)."""
    t0 = time.perf_counter()
    n, t1 = 0, None
    for batch in loader:
        if step is not None:
            step(batch)
        if t1 is None:
            t1 = time.perf_counter()
            continue
        n += batch["x"].shape[0]
    return t1 - t0, n / (time.perf_counter() - t1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=str(ROOT / "config" / "config.yaml"))
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--batches", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--device", default="auto", help="training (and rendering) device")
    ap.add_argument("--batch-images", type=int, default=None, help="simulation.render.batch_images")
    ap.add_argument("--out", type=Path, help="also write the table to this file")
    data = Path(os.environ.get("SUBSLOPE_DATA_MIRROR", ROOT / "resources"))
    ap.add_argument("--data", type=Path, default=data)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    device = pick_device(args.device)
    config = _config(args)
    config["simulation"]["render"]["device"] = device.type
    training = training_section(config)
    job = runnable_config(shard_job_config(config, "train"), config)
    model = build_model({"preset": "reduced"}, gamma_mean=2.0, gamma_std=0.52).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    loss_fn = NRELoss(model)

    def step(batch):
        loss = loss_fn(batch["gamma"].to(device), batch["x"].to(device))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    rows: dict[str, list[tuple[float, float]]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        shard = simulate_shard(job, "train", 0, Path(tmp) / "train.h5", progress=False)
        shards = ShardBatches([shard], args.batch, WHITENING, seed=1, drop_last=True)
        stream = training_stream(training, job)
        stream.whitening = WHITENING
        for r in range(args.repeats):
            shards.set_epoch(r)
            rows.setdefault("shards", []).append(_run(make_loader(shards), step))
            stream.set_epoch(r)
            for w in args.workers:
                loader = make_loader(stream, num_workers=w)
                rows.setdefault(f"stream, {w} worker(s)", []).append(_run(loader, step))
                loader = make_loader(stream, num_workers=w)
                rows.setdefault(f"stream only, {w} worker(s)", []).append(_run(loader, None))
    info = machine_info()
    lines = [
        f"machine: {info['cpu']}, {info['cores']} cores, torch {info['torch']}, {device}",
        f"load: {info['uptime']}",
        f"train scene of {Path(args.config).name}, reduced estimator, batches of {args.batch}, "
        f"{args.batches} batches a run, {args.repeats} runs, training process on 1 thread",
        "",
        "| training data | images/s (median) | min | max | start-up s (median) |",
        "|---|---|---|---|---|",
    ]
    for name, vals in rows.items():
        rates = [v[1] for v in vals]
        start = statistics.median(v[0] for v in vals)
        lines.append(
            f"| {name} | {statistics.median(rates):.1f} | {min(rates):.1f} | "
            f"{max(rates):.1f} | {start:.1f} |"
        )
    print("\n".join(lines))
    if args.out:
        args.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
