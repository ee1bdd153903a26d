"""Throughput on one accelerator: rendering at the mean training scene for several batch
sizes, and one optimiser step of the estimator with and without mixed precision.

Rendering: ``train`` scenes with N_sub = 1500 arc subhalos and LoS halos (δ_los = 1, the
prior mean), Sérsic sources, drawn on the CPU (:func:`_common.make_scene`), rendered with
the campaign's float32 settings on ``--device``; the first call of each batch size
compiles and is reported separately, then the median of ``--repeats`` calls.

Accuracy: the first image of each batch against the same parameters rendered on the CPU
in float64 with the reference settings (n_terms 30, direct sums, eager): max |Δ| in units
of the pixel noise σ and relative L2 (the budget: 0.1 σ and 1e-3). Peak GPU memory of
each row.

Training: one AdamW step (positives + rolled negatives, NRE loss, backward) of the
``--arch`` preset on random 1x100x100 images at ``--train-batch``: fp32, bf16 autocast,
bf16 + channels_last, and bf16 + channels_last + torch.compile; median of ``--steps``
steps after the warm-up (compilation reported apart). The last line turns the fastest
training rate into the GPU-hours of the paper-scale training (``config/paper.yaml``,
:func:`subslope.campaigns.cost.campaign_cost`).

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
from subslope.validation.scenes import image_errors, one_image  # noqa: E402


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


def _reset_peak(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)


def _peak_gib(device: torch.device) -> float:
    return torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else 0.0


def _accuracy(batch, image: torch.Tensor) -> tuple[float, float]:
    """Error of the first image of ``batch`` (rendered as ``image``) against its CPU
    float64 reference render."""
    one = one_image(batch, 0)
    ref = R.RenderSettings(
        device="cpu", dtype=torch.float64, n_terms=30, n_terms_main=30, compile="off",
        chunk_members=64, population="direct",
    )  # fmt: skip
    reference = R.render(one.macro, one.psf.cpu(), ref, subhalos=one.subhalos, los=one.los)
    return image_errors(image[None].cpu(), reference)


def render_rows(device: torch.device, batches, repeats: int, compile_mode: str) -> list[dict]:
    """Images/s of :func:`subslope.render.pipeline.render` per batch size: the batched
    path (batching 'auto') with ``batch_images`` = the batch size."""
    rows = []
    for n in batches:
        _reset_peak(device)
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
        image = R.render(*args, subhalos=subs, los=los)[0]
        max_sigma, rel = _accuracy(batch, image)
        rows.append(
            {
                "what": f"render N_sub=1500+LoS, batch {n}",
                "first_call_s": round(first, 3),
                "median_s": round(med, 4),
                "images_per_s": round(n / med, 1),
                "ms_per_image": round(1e3 * med / n, 3),
                "cpu_draw_s": round(draw, 2),
                "peak_gpu_gib": round(_peak_gib(device), 2),
                "max_dsigma": f"{max_sigma:.2e}",
                "rel_l2": f"{rel:.2e}",
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    return rows


#: Training variants: (name, bf16 autocast, channels_last, torch.compile).
TRAIN_VARIANTS = (
    ("fp32", False, False, False),
    ("bf16", True, False, False),
    ("bf16 channels_last", True, True, False),
    ("bf16 channels_last compiled", True, True, True),
)


def train_rows(device: torch.device, arch: str, batch: int, steps: int) -> list[dict]:
    """Images/s of one estimator optimiser step in each of :data:`TRAIN_VARIANTS`."""
    from subslope.nre.loss import NRELoss
    from subslope.nre.models import PRESETS, build_model, count_parameters

    rows = []
    for name, amp, channels_last, compiled in TRAIN_VARIANTS:
        torch.manual_seed(0)
        _reset_peak(device)
        model = build_model(PRESETS[arch], gamma_mean=2.0, gamma_std=0.52).to(device)
        fmt = torch.channels_last if channels_last else torch.contiguous_format
        model = model.to(memory_format=fmt)
        opt = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=1e-2)
        loss_fn = NRELoss(torch.compile(model) if compiled else model)
        x = torch.randn(batch, 1, 100, 100, device=device).to(memory_format=fmt)
        g = 1.1 + 1.8 * torch.rand(batch, device=device)
        step = (loss_fn, opt, g, x, amp)
        first = _timed(device, _train_step, *step)
        med = statistics.median(_timed(device, _train_step, *step) for _ in range(steps))
        rows.append(
            {
                "what": f"train step {arch} ({count_parameters(model):.2e} params), batch "
                f"{batch}, {name}",
                "first_call_s": round(first, 3),
                "median_s": round(med, 4),
                "images_per_s": round(batch / med, 1),
                "peak_gpu_gib": round(_peak_gib(device), 2),
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    return rows


def paper_gpu_hours(rows: list[dict]) -> str:
    """The paper-scale training's GPU-hours at the fastest measured training rate."""
    from subslope.campaigns.cost import campaign_cost
    from subslope.config import load

    rates = [r["images_per_s"] for r in rows if r["what"].startswith("train step")]
    if not rates:
        return ""
    root = Path(__file__).resolve().parents[1]
    paper = load(root / "config" / "paper.yaml", env=False)
    cost = campaign_cost(paper, gpu_images_per_s=max(rates))
    return (
        f"paper-scale training ({cost.training_images:,} images x {cost.max_epochs} epochs at "
        f"most) at {max(rates):.0f} images/s: {cost.gpu_hours_training:.1f} GPU-hours"
    )


def markdown(rows: list[dict], info: dict) -> str:
    keys = [
        "what", "images_per_s", "median_s", "ms_per_image", "first_call_s", "peak_gpu_gib",
        "max_dsigma", "rel_l2",
    ]  # fmt: skip
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
    hours = paper_gpu_hours(rows)
    text += f"\n{hours}\n" if hours else ""
    print(text)
    if args.out:
        Path(args.out).write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
