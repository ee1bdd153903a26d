"""Training throughput of the ratio estimator on this machine.

For each (model, threads, batch size) a fresh subprocess builds the model, runs
``--warmup`` then ``--steps`` optimiser steps (forward on positives + negatives,
NRE loss, backward, AdamW) on random 1×100×100 images, and reports images/s and the
peak resident memory above the post-build baseline (``ru_maxrss`` − RSS after
building the model, i.e. what one training batch costs). A separate measurement times
the data path alone (HDF5 shard → ShardBatches → whitened, masked batch).

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/train_speed.py            # full table
    .venv/bin/python benchmarks/train_speed.py --quick                      # smaller
    .venv/bin/python benchmarks/train_speed.py --json results.json

The epoch-time estimate is ``n_images / images_per_s`` for ``--epoch-images`` (4000).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time

CASES_FULL = [
    ("reduced", 1, 64),
    ("reduced", 2, 64),
    ("reduced", 1, 256),
    ("reduced", 2, 256),
    ("resnet50", 1, 16),
    ("resnet50", 2, 16),
    ("resnet50", 2, 64),
]
CASES_QUICK = [("reduced", 1, 64), ("reduced", 2, 64), ("resnet50", 2, 16)]


def _rss_bytes() -> int:
    import psutil

    return psutil.Process().memory_info().rss


def run_case(model_name: str, threads: int, batch: int, warmup: int, steps: int) -> dict:
    """Runs inside the subprocess: one configuration."""
    import torch

    from subslope.nre.loss import NRELoss
    from subslope.nre.models import PRESETS, build_model, count_parameters

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    model = build_model(PRESETS[model_name], gamma_mean=2.0, gamma_std=0.52)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=1e-2)
    loss_fn = NRELoss(model)
    x = torch.randn(batch, 1, 100, 100)
    g = 1.1 + 1.8 * torch.rand(batch)
    base = _rss_bytes()

    def step():
        loss = loss_fn(g, x)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    for _ in range(warmup):
        step()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    dt = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: KiB
    return {
        "model": model_name,
        "n_params": count_parameters(model),
        "threads": threads,
        "batch": batch,
        "steps": steps,
        "seconds": dt,
        "images_per_s": batch * steps / dt,
        "peak_rss_mib": peak / 2**20,
        "batch_mem_mib": max(peak - base, 0) / 2**20,
    }


def data_path_speed(n: int = 512, batch: int = 128) -> dict:
    """Images/s of reading + pre-processing from an HDF5 shard (single process)."""
    import h5py
    import numpy as np

    from subslope.nre.data import ShardBatches, make_loader

    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "s.h5")
        r = np.random.default_rng(0)
        with h5py.File(path, "w") as fh:
            fh.create_dataset(
                "images",
                data=r.normal(size=(n, 100, 100)).astype(np.float32),
                chunks=(16, 100, 100),
            )
            for k, lo, hi in (
                ("gamma_sub", 1.1, 2.9),
                ("theta_e", 0.9, 1.3),
                ("lens_x", -0.2, 0.2),
                ("lens_y", -0.2, 0.2),
            ):
                fh[f"params/{k}"] = r.uniform(lo, hi, n)
            fh.attrs["complete"] = True
        ds = ShardBatches([path], batch, (0.0, 1.0), shuffle=True, block_size=128)
        t0 = time.perf_counter()
        count = sum(b["x"].shape[0] for b in make_loader(ds))
        dt = time.perf_counter() - t0
    return {
        "what": "data path (HDF5 read + preprocess)",
        "images": count,
        "seconds": dt,
        "images_per_s": count / dt,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer cases and steps")
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--epoch-images", type=int, default=4000)
    ap.add_argument("--json", default=None, help="write the results here")
    ap.add_argument(
        "--case", nargs=3, metavar=("MODEL", "THREADS", "BATCH"), help=argparse.SUPPRESS
    )
    args = ap.parse_args(argv)

    if args.case:  # child process
        m, t, b = args.case
        print(json.dumps(run_case(m, int(t), int(b), args.warmup, args.steps or 3)))
        return 0

    cases = CASES_QUICK if args.quick else CASES_FULL
    results = []
    load_before = os.getloadavg()
    for m, t, b in cases:
        steps = args.steps or (3 if m == "resnet50" else 8)
        env = dict(os.environ, OMP_NUM_THREADS=str(t), MKL_NUM_THREADS=str(t))
        out = subprocess.run(
            [
                sys.executable,
                __file__,
                "--case",
                m,
                str(t),
                str(b),
                "--steps",
                str(steps),
                "--warmup",
                str(args.warmup),
            ],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        )
        res = json.loads(out.stdout.strip().splitlines()[-1])
        res["epoch_seconds_estimate"] = args.epoch_images / res["images_per_s"]
        results.append(res)
        print(
            f"{m:9s} params={res['n_params']:>9,d} threads={t} batch={b:4d}: "
            f"{res['images_per_s']:8.1f} img/s, "
            f"batch memory {res['batch_mem_mib']:7.0f} MiB (peak RSS {res['peak_rss_mib']:.0f} "
            "MiB), "
            f"epoch of {args.epoch_images} images ≈ {res['epoch_seconds_estimate']:.0f} s",
            flush=True,
        )
    data = data_path_speed()
    print(f"data path: {data['images_per_s']:.0f} img/s (read + preprocess, 1 process)")
    meta = {
        "machine": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "loadavg_before": load_before,
        "loadavg_after": os.getloadavg(),
        "python": sys.version.split()[0],
    }
    import torch

    meta["torch"] = torch.__version__
    print(json.dumps(meta))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"meta": meta, "results": results, "data_path": data}, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
