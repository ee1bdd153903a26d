"""Throughput on one accelerator: rendering at the mean training scene for several batch
sizes, and one optimiser step of the estimator with and without mixed precision.

Rendering: ``train`` scenes with N_sub = 1500 arc subhalos and LoS halos (δ_los = 1, the
prior mean), Sérsic sources, drawn on the CPU (:func:`_common.make_scene`), rendered with
the campaign's float32 settings on ``--device``; the first call of each batch size
compiles and is reported separately, then the median of ``--repeats`` calls.

Training: one AdamW step (positives + rolled negatives, NRE loss, backward) of the
``--arch`` preset on random 1x100x100 images at ``--train-batch``, fp32 and AMP (bf16 on
CUDA), median of ``--steps`` steps after one warm-up.

    .venv/bin/python benchmarks/gpu_throughput.py --device cuda --out results.md
    .venv/bin/python benchmarks/gpu_throughput.py --device cpu --batches 2 --train-batch 8 \
        --arch reduced --repeats 1 --steps 1        # a quick look on a CPU
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine_info, make_scene  # noqa: E402

from subslope.render import pipeline as R  # noqa: E402


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _timed(device: torch.device, fn, *args, **kwargs) -> float:
    """Wall time of ``fn(*args, **kwargs)`` in seconds, the device synchronised."""
    _sync(device)
    t0 = time.perf_counter()
    fn(*args, **kwargs)
    _sync(device)
    return time.perf_counter() - t0


def _train_step(loss_fn, opt, g: torch.Tensor, x: torch.Tensor, amp: bool) -> None:
    """One AdamW step of the NRE loss (bf16 autocast when ``amp``)."""
    with torch.autocast(x.device.type, dtype=torch.bfloat16, enabled=amp):
        loss = loss_fn(g, x)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()


def render_rows(device: torch.device, batches, repeats: int, compile_mode: str) -> list[dict]:
    """Images/s of :func:`subslope.render.pipeline.render` per batch size: the batched
    path (batching 'auto') with ``batch_images`` = the batch size."""
    rows = []
    for n in batches:
        settings = R.RenderSettings(device=str(device), compile=compile_mode, batch_images=n)
        t = time.perf_counter()
        batch = make_scene("train", n_img=n, n_sub=1500, with_los=True, seed=n)
        draw = time.perf_counter() - t
        psf = batch.psf.to(device)
        subs, los = batch.subhalos, batch.los  # numpy: render moves them to the device

        args = (batch.macro, psf, settings)
        first = _timed(device, R.render, *args, subhalos=subs, los=los)
        times = [_timed(device, R.render, *args, subhalos=subs, los=los) for _ in range(repeats)]
        med = statistics.median(times)
        rows.append(
            {
                "what": f"render N_sub=1500+LoS, batch {n}",
                "first_call_s": round(first, 3),
                "median_s": round(med, 4),
                "images_per_s": round(n / med, 1),
                "ms_per_image": round(1e3 * med / n, 3),
                "cpu_draw_s": round(draw, 2),
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    return rows


def train_rows(device: torch.device, arch: str, batch: int, steps: int) -> list[dict]:
    """Images/s of one estimator optimiser step, fp32 and AMP."""
    from subslope.nre.loss import NRELoss
    from subslope.nre.models import PRESETS, build_model, count_parameters

    rows = []
    for amp in (False, True):
        torch.manual_seed(0)
        model = build_model(PRESETS[arch], gamma_mean=2.0, gamma_std=0.52).to(device)
        opt = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=1e-2)
        loss_fn = NRELoss(model)
        x = torch.randn(batch, 1, 100, 100, device=device)
        g = 1.1 + 1.8 * torch.rand(batch, device=device)
        step = (loss_fn, opt, g, x, amp)
        _timed(device, _train_step, *step)
        med = statistics.median(_timed(device, _train_step, *step) for _ in range(steps))
        peak = torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else 0.0
        rows.append(
            {
                "what": f"train step {arch} ({count_parameters(model):.2e} params), batch "
                f"{batch}, {'AMP bf16' if amp else 'fp32'}",
                "median_s": round(med, 4),
                "images_per_s": round(batch / med, 1),
                "peak_gpu_gib": round(peak, 2),
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    return rows


def markdown(rows: list[dict], info: dict) -> str:
    keys = ["what", "images_per_s", "median_s", "ms_per_image", "first_call_s", "peak_gpu_gib"]
    lines = [
        f"machine: {info}",
        "",
        "| " + " | ".join(keys) + " |",
        "|" + "---|" * len(keys),
    ]
    for r in rows:
        lines.append("| " + " | ".join(str(r.get(k, "")) for k in keys) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--batches", default="64,128,256,512,1024")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--compile", choices=("auto", "on", "off"), default="auto")
    ap.add_argument("--arch", default="resnet50")
    ap.add_argument("--train-batch", type=int, default=1000)
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--skip-render", action="store_true")
    ap.add_argument("--skip-train", action="store_true")
    ap.add_argument("--out", default=None, help="markdown table written here")
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    info = machine_info()
    if device.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
    rows = []
    if not args.skip_render:
        batches = [int(b) for b in args.batches.split(",")]
        rows += render_rows(device, batches, args.repeats, args.compile)
    if not args.skip_train:
        rows += train_rows(device, args.arch, args.train_batch, args.steps)
    text = markdown(rows, info)
    print(text)
    if args.out:
        Path(args.out).write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
