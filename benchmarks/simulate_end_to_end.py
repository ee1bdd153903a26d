"""End-to-end cost of a training shard per image: sampling, placement (the smooth model
of an N_sub = 0 render), render, noise and write, as the workflow's shard job spends it.

Each repeat simulates ``--images`` images of the ``train`` scene of ``--config`` with
N_sub fixed at ``--n-sub`` and δ_los fixed at 1 (the prior mean), through
:func:`subslope.simulation.shard.simulate_shard` (compile 'on', warm inductor cache after
the first repeat, which is left out), one thread, and reads the timings the shard job
logs. With ``--lenstronomy K`` each repeat also renders (and adds noise to) ``K`` images
of the same kind of scene with lenstronomy (``benchmarks/simulate_vs_lenstronomy.py``'s
model: train preset, N_sub = ``--n-sub`` + LoS, Sérsic source, γ = 2), alternating with
subslope's shard, so that both see the same load; the ratio of lenstronomy's render-only
time to subslope's end-to-end time is printed. Prints per-image medians over
``--repeats`` repeats.

    OMP_NUM_THREADS=1 SUBSLOPE_DATA_MIRROR=../shared/data \\
        .venv/bin/python benchmarks/simulate_end_to_end.py [--images 32] [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine_info  # noqa: E402

from subslope import config as C  # noqa: E402
from subslope.io.shards import write_shard  # noqa: E402
from subslope.simulation import shard as S  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("sampling", "smooth", "render", "noise", "write", "setup")


def _config(args) -> dict:
    over = {
        "data": {"resources_dir": str(args.data)},
        "scenes": {
            "train": {
                "subhalos": {"count": args.n_sub},
                "los": {"delta_los": 1.0},
            }
        },
        "simulation": {
            "scenes": {"train": {"n_shards": 1, "images_per_shard": args.images}},
            "render": {
                "compile": args.compile,
                "batch_images": args.batch,
                "batching": args.batching,
            },
            "shard_cache": None,
        },
    }
    return C.load(args.config, overrides=over, env=False)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=str(ROOT / "config" / "config.yaml"))
    ap.add_argument("--images", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--n-sub", type=int, default=1500)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--compile", choices=("auto", "on", "off"), default="on")
    ap.add_argument(
        "--batching",
        choices=("auto", "per_image", "sub_batch"),
        default="auto",
        help="simulation.render.batching; sub_batch sizes batches from max_elements, "
        "which is one image at N_sub = 1500 on the CPU",
    )
    ap.add_argument("--lenstronomy", type=int, default=0, metavar="K")
    data = Path(os.environ.get("SUBSLOPE_DATA_MIRROR", ROOT / "resources"))
    ap.add_argument("--data", type=Path, default=data)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    config = _config(args)
    rows: dict[str, list[float]] = {k: [] for k in (*STAGES, "total", "file_kb")}
    reference = _lenstronomy(args) if args.lenstronomy else None
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats + 1):
            if reference is not None:
                t = time.perf_counter()
                reference()
                if r:
                    rows.setdefault("lenstronomy", []).append(
                        1e3 * (time.perf_counter() - t) / args.lenstronomy
                    )
            path = Path(tmp) / f"shard_{r}.h5"
            seq = np.random.SeedSequence(entropy=r, spawn_key=(7,))
            t = time.perf_counter()
            out = S.simulate_images(config, "train", args.images, seq)
            tw = time.perf_counter()
            write_shard(
                path, **{k: out[k] for k in ("images", "params", "psf", "subhalos", "los")},
                sources=out["sources"] or None, attrs={"scene": "train"}, overwrite=True,
            )  # fmt: skip
            timings = dict(out["timings"], write=time.perf_counter() - tw)
            timings["total"] = time.perf_counter() - t
            if r == 0:
                continue  # compiles (or loads the cache): the first job's cost
            for k in (*STAGES, "total"):
                rows[k].append(1e3 * timings.get(k, 0.0) / args.images)
            rows["file_kb"].append(path.stat().st_size / 1e3 / args.images)
    info = machine_info()
    print(f"machine: {info['cpu']}, {info['cores']} cores, torch {info['torch']}")
    print(f"load: {info['uptime']}")
    print(f"{args.images} images x {args.repeats} repeats, N_sub = {args.n_sub} + LoS, "
          f"compile {args.compile}, batch {args.batch}, batching {args.batching}")  # fmt: skip
    print("| per image | median | min | max |")
    print("|---|---|---|---|")
    for k, v in rows.items():
        unit = "KB" if k == "file_kb" else "ms"
        name = "lenstronomy render + noise" if k == "lenstronomy" else k
        print(f"| {name} ({unit}) | {statistics.median(v):.2f} | {min(v):.2f} | {max(v):.2f} |")
    if reference is not None:
        ratio = statistics.median(rows["lenstronomy"]) / statistics.median(rows["total"])
        print(f"lenstronomy render-only / subslope end to end: {ratio:.1f}x")
    return 0


def _lenstronomy(args):
    """A callable rendering ``--lenstronomy`` images with lenstronomy, plus noise."""
    import _common as common

    from subslope.validation.lenstronomy import lenstronomy_model, lenstronomy_noise

    batch = common.make_scene(
        "train", args.lenstronomy, args.n_sub, True, seed=0, gamma_label=2.0, delta_los=1.0
    )
    models = [
        lenstronomy_model(batch.macro, batch.psf, i, subhalos=batch.subhalos, los=batch.los)
        for i in range(batch.n)
    ]
    band = lenstronomy_noise()
    rng = np.random.default_rng(0)
    for m in models:
        m.image()  # numba compiles on first use

    def run():
        for m in models:
            im = m.image()
            im + band.noise_for_model(im, seed=int(rng.integers(2**31)))

    return run


if __name__ == "__main__":
    sys.exit(main())
