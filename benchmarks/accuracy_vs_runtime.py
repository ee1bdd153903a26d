"""Error vs seconds per image for every numerical knob of subslope's renderer.

Scene: the mean training scene (train preset, Sérsic source, N_sub = 1500 on the arc,
DG19 EPL LoS with δ_los = 1, the mean of its prior), ``--n-img`` images. Each setting
varies one knob of the default ``RenderSettings`` (plus a few combinations) and is
compared with a high-accuracy reference of the same parameters: float64,
n_terms = n_terms_main = 30, eager, direct (conv2d) convolution, **the same
supersampling**. For the supersampling rows a second error is given against a
float64, k = ``--k-ref`` render (the pixel-integration error of the image itself).
The COSMOS-stamp interpolation knob is measured on a second scene with real galaxies.

Timing: median (and min) wall time per image over ``--repeats`` repeats, one thread,
after two warm-up calls (torch.compile, and the recompiles of shapes seen for the first
time, happen there). The default is measured first and again last, to show the drift.
Output: a markdown table, a CSV (``--csv``) and a Pareto plot (``--plot``, PNG and PDF):
seconds/image against max |Δ|/σ_noise and against relative L2, the Pareto front of
(time, error) and the default marked.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/accuracy_vs_runtime.py \
        --csv docs/performance_knobs.csv --plot docs/performance_pareto.png

``--scene nfw:12000 --knobs population,split`` measures the population knobs on a
reference CDM scene instead (NFW subhalos everywhere, N_sub = 12,000, LoS; only the
settings whose label holds one of the given words, the default first and last).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import os
import sys
import time
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from subslope.render import kernels  # noqa: E402
from subslope.render import pipeline as R  # noqa: E402

F64 = torch.float64

#: (label, RenderSettings overrides). The first entry is the default.
KNOBS: list[tuple[str, dict]] = [
    ("default", {}),
    ("dtype=float64", {"dtype": F64}),
    ("population=direct", {"population": "direct"}),
    ("split_tolerance=5e-6", {"split_tolerance": 5e-6}),
    ("split_tolerance=1e-5", {"split_tolerance": 1e-5}),
    ("split_tolerance=4e-5", {"split_tolerance": 4e-5}),
    ("split_tolerance=1e-4", {"split_tolerance": 1e-4}),
    ("split_tolerance=3e-4", {"split_tolerance": 3e-4}),
    ("split_spacing=3", {"split_spacing": 3}),
    ("split_spacing=3, split_tolerance=1e-5", {"split_spacing": 3, "split_tolerance": 1e-5}),
    ("split_spacing=4", {"split_spacing": 4}),
    ("split_order=4", {"split_order": 4}),
    ("split_order=8", {"split_order": 8}),
    ("n_terms=4", {"n_terms": 4}),
    ("n_terms=6", {"n_terms": 6}),
    ("n_terms=10", {"n_terms": 10}),
    ("n_terms=14", {"n_terms": 14}),
    ("n_terms_main=8", {"n_terms_main": 8}),
    ("n_terms_main=20", {"n_terms_main": 20}),
    ("population=direct, chunk=64", {"population": "direct", "chunk_members": 64}),
    ("compile=off", {"compile": "off"}),
    ("compile=off, population=direct", {"compile": "off", "population": "direct"}),
    ("convolution=direct", {"convolution": "direct"}),
    ("supersample=2", {"supersample": 2}),
    ("supersample=3", {"supersample": 3}),
    ("n_terms=6, split_tolerance=4e-5", {"n_terms": 6, "split_tolerance": 4e-5}),
    (
        "float64, population=direct, n_terms=14, n_terms_main=20",
        {"dtype": F64, "population": "direct", "n_terms": 14, "n_terms_main": 20},
    ),
    ("default (again, last: load drift check)", {}),
]
INTERP = [
    ("source_interpolation=bilinear (default)", {}),
    ("source_interpolation=bicubic", {"source_interpolation": "bicubic"}),
    ("source_interpolation=nearest", {"source_interpolation": "nearest"}),
]


def ref_of(settings: R.RenderSettings) -> R.RenderSettings:
    return dataclasses.replace(
        settings,
        dtype=F64,
        n_terms=30,
        n_terms_main=30,
        compile="off",
        chunk_members=16,
        convolution="direct",
        population="direct",
        source_interpolation=settings.source_interpolation,
    )


def fresh_compile() -> None:
    """Each setting gets its own torch.compile of the population kernels, so that no
    setting is timed with graphs (or a recompile-limit fallback) left by another."""
    torch._dynamo.reset()
    kernels.clear_cache()


def time_it(fn, repeats: int, n: int) -> tuple[float, float]:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t0) / n)
    return float(np.median(ts)), float(np.min(ts))


def run(args) -> list[dict]:
    base = R.RenderSettings(device="cpu")
    kind, n_sub = args.scene.split(":")
    batch = C.make_scene(kind, args.n_img, int(n_sub), True, seed=args.seed, delta_los=1.0)
    knobs = KNOBS
    if args.knobs:
        words = args.knobs.split(",")
        knobs = [k for k in KNOBS if k[0].startswith("default") or any(w in k[0] for w in words)]
    refs: dict[int, torch.Tensor] = {}
    rows = []
    hi = None
    if args.k_ref:
        t0 = time.perf_counter()
        hi = batch.render(
            dataclasses.replace(ref_of(base), supersample=args.k_ref, chunk_members=8)
        )
        print(f"k={args.k_ref} float64 reference: {time.perf_counter() - t0:.0f} s", flush=True)
    for label, over in knobs:
        s = dataclasses.replace(base, **over)
        if s.supersample not in refs:
            refs[s.supersample] = batch.render(ref_of(s))
        fresh_compile()
        img = batch.render(s)  # warm-up / compile
        batch.render(s)  # second warm-up: graphs specialised on first sight of a shape
        med, mn = time_it(lambda s=s: batch.render(s), args.repeats, batch.n)
        es, el = C.image_errors(img, refs[s.supersample])
        row = {
            "setting": label,
            "scene": batch.name,
            "s_per_img": med,
            "s_min": mn,
            "max_sigma": es,
            "rel_l2": el,
            "load": C.load(),
        }
        if hi is not None and (label == "default" or "supersample" in label):
            row["max_sigma_vs_kref"], row["rel_l2_vs_kref"] = C.image_errors(img, hi)
        rows.append(row)
        print(fmt(row), flush=True)
    if not args.no_cosmos:
        try:
            cb = cosmos_batch(args)
        except Exception as exc:  # pragma: no cover - data folder missing
            print(f"COSMOS scene skipped: {exc}")
            return rows
        for label, over in INTERP:
            s = dataclasses.replace(base, **over)
            ref = R.render(
                cb.macro,
                cb.psf,
                ref_of(dataclasses.replace(s, source_interpolation="bicubic")),
                sources=cb.sources,
                subhalos=cb.subhalos,
                los=cb.los,
            )
            fn = lambda cb=cb, s=s: R.render(
                cb.macro, cb.psf, s, sources=cb.sources, subhalos=cb.subhalos, los=cb.los
            )
            fresh_compile()
            img = fn()
            med, mn = time_it(fn, args.repeats, len(cb.macro["z_lens"]))
            es, el = C.image_errors(img, ref)
            row = {
                "setting": label,
                "scene": "train N_sub=1500 +LoS, COSMOS source (ref: bicubic f64)",
                "s_per_img": med,
                "s_min": mn,
                "max_sigma": es,
                "rel_l2": el,
                "load": C.load(),
            }
            rows.append(row)
            print(fmt(row), flush=True)
    return rows


@dataclasses.dataclass
class _CosmosBatch:
    macro: dict
    psf: torch.Tensor
    sources: R.PixelatedSources
    subhalos: object
    los: object


def cosmos_batch(args) -> _CosmosBatch:
    b = C.make_scene("train", args.n_img, 1500, True, seed=args.seed, delta_los=1.0)
    macro = {
        k: v
        for k, v in b.macro.items()
        if not k.startswith("src_") or k in ("src_x", "src_y", "src_rotation")
    }
    src = C._rs.cosmos_sources(macro, np.random.default_rng(args.seed))
    return _CosmosBatch(macro, b.psf, src, b.subhalos, b.los)


def fmt(r: dict) -> str:
    extra = ""
    if "max_sigma_vs_kref" in r:
        extra = f"{r['max_sigma_vs_kref']:.2e} / {r['rel_l2_vs_kref']:.1e}"
    return (
        f"| {r['setting']} | {r['s_per_img']:.4f} ({r['s_min']:.4f}) | {r['max_sigma']:.2e} | "
        f"{r['rel_l2']:.1e} | "
        f"{extra} | {r['load']} |"
    )


def pareto(points: np.ndarray) -> np.ndarray:
    """Indices of the non-dominated (time, error) points, sorted by time."""
    order = np.argsort(points[:, 0])
    front, best = [], np.inf
    for i in order:
        if points[i, 1] < best:
            front.append(i)
            best = points[i, 1]
    return np.asarray(front)


def plot(rows: list[dict], path: str) -> None:
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in rows if "COSMOS" not in r["scene"]]
    t = np.array([r["s_per_img"] for r in rows])
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    for ax, key, budget, lab in (
        (axes[0], "max_sigma", 0.1, r"max $|\Delta|/\sigma_{\rm noise}$"),
        (axes[1], "rel_l2", 1e-3, "relative L2"),
    ):
        e = np.maximum(np.array([r[key] for r in rows]), 1e-16)
        ax.scatter(t, e, s=14, c="0.5", zorder=2)
        f = pareto(np.stack([t, e], 1))
        ax.step(t[f], e[f], where="post", c="C0", lw=1, zorder=1, label="Pareto front")
        ax.scatter(t[f], e[f], s=22, c="C0", zorder=3)
        ax.scatter(t[0], e[0], s=160, marker="*", c="C3", zorder=4, label="default")
        ax.axhline(budget, c="C3", ls="--", lw=0.8, label=f"budget {budget:g}")
        for ti, ei, r in zip(t, e, rows):
            ax.annotate(
                r["setting"].replace("supersample", "k").replace("n_terms", "nt"),
                (ti, ei),
                fontsize=5.5,
                xytext=(3, 2),
                textcoords="offset points",
            )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xticks(
            [
                v
                for v in (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0)
                if t.min() / 1.5 <= v <= t.max() * 1.5
            ]
        )
        ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.set_xlabel("s / image (1 CPU thread, median)")
        ax.set_ylabel(lab)
        ax.legend(fontsize=7, loc="upper right")
    fig.suptitle(
        f"subslope render: {rows[0]['scene']}, error vs float64/n_terms=30 reference (same "
        "supersampling)",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    fig.savefig(str(Path(path).with_suffix(".pdf")))
    print(f"saved {path} and .pdf")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n-img", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument(
        "--k-ref",
        type=int,
        default=4,
        help="supersampling of the pixel-integration reference (0: skip)",
    )
    ap.add_argument("--no-cosmos", action="store_true")
    ap.add_argument(
        "--scene", default="train:1500", help="kind:N_sub of the scene (train, nfw or tnfw)"
    )
    ap.add_argument(
        "--knobs", default=None, help="comma-separated words: only the settings naming one"
    )
    ap.add_argument("--csv", default=None)
    ap.add_argument("--plot", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(C.machine_info())
    print(
        "| setting | s/img median (min) | max \\|Δ\\|/σ | rel L2 | vs k_ref: max/σ / rel L2 | "
        "load |"
    )
    print("|---|---|---|---|---|---|")
    t0 = time.perf_counter()
    rows = run(args)
    print(f"total {time.perf_counter() - t0:.0f} s, load {C.load()}")
    if args.csv:
        keys = [
            "setting",
            "scene",
            "s_per_img",
            "s_min",
            "max_sigma",
            "rel_l2",
            "max_sigma_vs_kref",
            "rel_l2_vs_kref",
            "load",
        ]
        with open(args.csv, "w", newline="") as f:
            w = csv.DictWriter(f, keys, extrasaction="ignore")
            w.writeheader()
            for r in rows:
                w.writerow({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in r.items()})
    if args.plot:
        plot(rows, args.plot)


if __name__ == "__main__":
    main()
