"""subslope's renderer against lenstronomy 1.14.2 on the same sampled scenes.

For each scene (train preset, EPL subhalos on the arc, with N_sub in {0, 100, 1500,
3000}, LoS off/on; the NFW and tNFW CDM scenes at N_sub = 1500 and 3000; and EPL, NFW
and tNFW at N_sub = 6000 and 12000, the sizes of the reference CDM sets, all with LoS),
the same parameters are rendered by
:func:`subslope.render.pipeline.render` (default RenderSettings) and by a lenstronomy
``ImageModel`` built by ``benchmarks/_common.py`` (EPL_NUMBA / NFW / TNFW, SHEAR,
MULTIPOLE m=3,4, CONVERGENCE sheets, ``MultiPlane`` for LoS, SERSIC_ELLIPSE source and
lens light, PIXEL PSF, supersampling 1). Both timings include the noise draw
(subslope ``instrument.add_noise``; lenstronomy ``SingleBand.noise_for_model``).
Timing repeats alternate the two codes so that both see the same machine load; the
reported numbers are medians (and minima) of per-image wall time over ``--repeats``.
The lenstronomy model set-up (incl. the sheet κ pass) is not timed.

Errors (noise-free images): max |Δ| / σ_noise (σ from ``instrument.noise_sigma_map`` of
lenstronomy's image) and relative L2, worst over the images of the scene; the default
render against subslope's float64 / n_terms = 30 / direct-sum reference (max |Δ| / σ of
the reference's noise), and that reference against lenstronomy (relative L2)
(``--no-ref64`` skips both).

The label γ of the train scenes is fixed (``--gamma``, default 2.0) so that every EPL
member has θ_E = amp^(1/(γ−1)) representable in float64 (lenstronomy's parametrisation);
scenes that still contain an unrepresentable member are reported as such.

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 .venv/bin/python benchmarks/simulate_vs_lenstronomy.py \
        --csv docs/performance_vs_lenstronomy.csv
    ... --breakdown        # stage timers of the default render at N_sub = 1500 + LoS
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import os
import sys
import time
import warnings
from collections import defaultdict
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from subslope.physics.instrument import add_noise  # noqa: E402
from subslope.render import nearfar as NF  # noqa: E402
from subslope.render import pipeline as R  # noqa: E402
from subslope.validation.lenstronomy import (  # noqa: E402
    LensModelUnrepresentable,
    lenstronomy_model,
    lenstronomy_noise,
)  # noqa: E402

warnings.filterwarnings("ignore", message="Cosmology is provided")

SCENES = (
    [("train", n, los) for n in (0, 100, 1500, 3000) for los in (False, True)]
    + [("nfw", 1500, True), ("tnfw", 1500, True)]
    + [(kind, n, True) for n in (6000, 12000) for kind in ("train", "nfw", "tnfw")]
    + [("nfw", 3000, True), ("tnfw", 3000, True)]
)


def compare_scene(kind, n_sub, with_los, args, settings, ref_settings) -> dict:
    batch = C.make_scene(
        kind,
        args.n_img,
        n_sub,
        with_los,
        seed=args.seed,
        gamma_label=args.gamma if kind == "train" else None,
        delta_los=args.delta_los,
    )
    row = {
        "scene": batch.name,
        "n_img": batch.n,
        "n_sub": n_sub,
        "los_halos": 0.0 if batch.los is None else float(np.mean(batch.los.counts)),
    }
    try:
        models = [
            lenstronomy_model(batch.macro, batch.psf, i, subhalos=batch.subhalos, los=batch.los)
            for i in range(batch.n)
        ]
    except LensModelUnrepresentable as exc:
        row["note"] = str(exc)
        return row
    row["planes"] = float(np.mean([m.n_planes for m in models]))
    band = lenstronomy_noise()
    load0 = C.load()
    ours = batch.render(settings)  # warm-up (torch.compile on first use)
    theirs = np.stack([m.image() for m in models])  # warm-up (numba JIT on first use)
    gen = torch.Generator().manual_seed(0)
    rs = np.random.default_rng(0)
    t_ours, t_theirs = [], []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        img = batch.render(settings)
        add_noise(img, gen)
        t_ours.append((time.perf_counter() - t0) / batch.n)
        t0 = time.perf_counter()
        for m in models:
            im = m.image()
            im + band.noise_for_model(im, seed=int(rs.integers(2**31)))
        t_theirs.append((time.perf_counter() - t0) / batch.n)
    row["load"] = f"{load0} -> {C.load()}"
    th = torch.as_tensor(theirs)
    row["max_sigma"], row["rel_l2"] = C.image_errors(ours, th)
    if not args.no_ref64:
        ref = batch.render(ref_settings)
        row["rel_l2_ref64"] = C.image_errors(ref, th)[1]
        row["max_sigma_vs_ref64"], row["rel_l2_vs_ref64"] = C.image_errors(ours, ref)
    row.update(
        ours_med=float(np.median(t_ours)),
        ours_min=float(np.min(t_ours)),
        len_med=float(np.median(t_theirs)),
        len_min=float(np.min(t_theirs)),
    )
    row["ratio"] = row["len_med"] / row["ours_med"]
    return row


def fmt_row(r: dict) -> str:
    if "note" in r:
        return f"| {r['scene']} | – | – | – | – | – | – | – | – | {r['note']} |"
    ref = f"{r['rel_l2_ref64']:.1e}" if "rel_l2_ref64" in r else "–"
    own = f"{r['max_sigma_vs_ref64']:.1e}" if "max_sigma_vs_ref64" in r else "–"
    return (
        f"| {r['scene']} | {r['los_halos']:.1f} | {r['ours_med']:.4f} ({r['ours_min']:.4f}) | "
        f"{r['len_med']:.3f} ({r['len_min']:.3f}) | **{r['ratio']:.1f}×** | {r['max_sigma']:.1e} | "
        f"{r['rel_l2']:.1e} | {own} | {ref} | {r['load']} |"
    )


# ---------------------------------------------------------------------------- breakdown
def breakdown(args, settings) -> None:
    """Inclusive wall time per render stage of the default settings (timers around the
    stage functions of subslope.render.pipeline, monkeypatched; one thread)."""
    batch = C.make_scene(
        "train",
        args.n_img,
        1500,
        True,
        seed=args.seed,
        gamma_label=args.gamma,
        delta_los=args.delta_los,
    )
    acc: dict[str, float] = defaultdict(float)
    calls: dict[str, int] = defaultdict(int)
    state = {"stage": None}
    orig = {
        n: getattr(R, n)
        for n in (
            "population_pass",
            "main_lens_deflection",
            "shear_deflection",
            "multipole_deflection",
            "sersic_ellipse_from_magnitude",
            "convolve",
            "multi_plane_ray_shoot",
            "pixelated_light",
            "count_step",
            "pack_population",
            "flat_table",
        )
    }
    orig_nf = {
        n: getattr(NF, n) for n in ("member_rungs", "near_pairs", "near_on_tiles", "far_on_tiles")
    }

    def timed(name, fn, label=None):
        def w(*a, **k):
            t0 = time.perf_counter()
            out = fn(*a, **k)
            key = label(a) if label else name
            acc[key] += time.perf_counter() - t0
            calls[key] += 1
            return out

        return w

    def stage(name):
        state["stage"] = name
        orig["count_step"](name)

    R.count_step = stage
    R.population_pass = timed(
        "pop",
        orig["population_pass"],
        lambda a: f"population pass: {state['stage']} ({a[0].profile})",
    )
    NF.member_rungs = timed("  split: member radii (circle peaks)", orig_nf["member_rungs"])
    NF.near_pairs = timed("  split: tile lists", orig_nf["near_pairs"])
    NF.near_on_tiles = timed("  split: near field on tiles", orig_nf["near_on_tiles"])
    NF.far_on_tiles = timed("  split: exact far field in rough tiles", orig_nf["far_on_tiles"])
    R.main_lens_deflection = timed("main-lens EPL (n_terms_main)", orig["main_lens_deflection"])
    R.shear_deflection = timed("shear", orig["shear_deflection"])
    R.multipole_deflection = timed("multipoles", orig["multipole_deflection"])
    R.sersic_ellipse_from_magnitude = timed(
        "Sérsic (source + lens light)", orig["sersic_ellipse_from_magnitude"]
    )
    R.convolve = timed("PSF convolution", orig["convolve"])
    R.pack_population = timed("member tables (subhalos)", orig["pack_population"])
    R.flat_table = timed("member tables (LoS)", orig["flat_table"])
    try:
        batch.render(settings)  # warm-up / compile
        acc.clear()
        calls.clear()
        tot = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            batch.render(settings)
            tot.append(time.perf_counter() - t0)
    finally:
        for n, f in orig.items():
            setattr(R, n, f)
        for n, f in orig_nf.items():
            setattr(NF, n, f)
    per = args.repeats * batch.n
    total = sum(tot) / per
    n_sub = np.asarray(batch.subhalos.counts)
    print(
        f"\nbreakdown, {batch.name}, {batch.n} images x {args.repeats} repeats, load {C.load()}, "
        f"mean LoS halos {np.mean(batch.los.counts):.1f}"
    )
    print("| stage | ms/image | share | calls/image |\n|---|---|---|---|")
    for k, v in sorted(acc.items(), key=lambda kv: -kv[1]):
        print(
            f"| {k} | {1e3 * v / per:.1f} | {100 * v / per / total:.0f}% | {calls[k] / per:.0f} |"
        )
    # the population passes of LoS sit inside nothing else timed; the split's parts sit inside the
    # pass
    inner = sum(v for k, v in acc.items() if not k.startswith("  "))
    print(
        "| rest (Python glue, grids, multi-plane recursion, binning) | "
        f"{1e3 * (total - inner / per):.1f} | "
        f"{100 * (1 - inner / per / total):.0f}% | |"
    )
    print(f"| **total** | **{1e3 * total:.1f}** | | |")
    pairs = float(np.mean(n_sub)) * settings.npix**2
    sub = [v for k, v in acc.items() if k.startswith("population pass: subhalos")]
    if sub:
        print(
            f"subhalo pass: {1e9 * sub[0] / per / pairs:.1f} ns per pixel-subhalo pair of the "
            "direct sum "
            f"(population method: {settings.population})"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--n-img", type=int, default=2, help="images per scene (rendered by both codes)"
    )
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument(
        "--threads", type=int, default=1, help="torch threads for subslope (numba stays serial)"
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--gamma", type=float, default=2.0, help="label γ of the train scenes")
    ap.add_argument("--delta-los", type=float, default=1.0, help="δ_los (1.0 = mean of U(0, 2))")
    ap.add_argument(
        "--scenes",
        default=None,
        help="subset, e.g. 'train:1500:1,nfw:1500:1' (kind:N_sub:LoS); default: all 10",
    )
    ap.add_argument(
        "--no-ref64", action="store_true", help="skip the float64 subslope reference column"
    )
    ap.add_argument("--csv", default=None)
    ap.add_argument(
        "--batch-images",
        type=int,
        default=None,
        help="RenderSettings.batch_images (default: the schema's; 1 = one image at a time)",
    )
    ap.add_argument(
        "--breakdown", action="store_true", help="only the stage breakdown at N_sub = 1500 + LoS"
    )
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    settings = R.RenderSettings(device="cpu")
    if args.batch_images is not None:
        settings = dataclasses.replace(settings, batch_images=args.batch_images)
    ref_settings = C.reference_settings(settings)
    print(C.machine_info())
    print(f"settings: {settings}")
    if args.breakdown:
        breakdown(args, settings)
        return
    todo = (
        SCENES
        if args.scenes is None
        else [
            (k, int(n), bool(int(with_los)))
            for k, n, with_los in (s.split(":") for s in args.scenes.split(","))
        ]
    )
    print(
        "| scene | mean LoS halos | subslope s/img median (min) | lenstronomy s/img median (min) "
        "| ratio "
        "(median) | max \\|Δ\\|/σ | rel L2 | max \\|Δ\\|/σ vs f64 ref | rel L2 f64 ref "
        "| load 1/5/15 before -> after |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    t_start = time.perf_counter()
    for kind, n_sub, los in todo:
        r = compare_scene(kind, n_sub, los, args, settings, ref_settings)
        rows.append(r)
        print(fmt_row(r), flush=True)
    print(
        f"total {time.perf_counter() - t_start:.0f} s; uptime after: {C.machine_info()['uptime']}"
    )
    if args.csv:
        keys = [
            "scene",
            "n_img",
            "n_sub",
            "los_halos",
            "planes",
            "ours_med",
            "ours_min",
            "len_med",
            "len_min",
            "ratio",
            "max_sigma",
            "rel_l2",
            "rel_l2_ref64",
            "max_sigma_vs_ref64",
            "rel_l2_vs_ref64",
            "load",
            "note",
        ]
        with open(args.csv, "w", newline="") as f:
            w = csv.DictWriter(f, keys, extrasaction="ignore")
            w.writeheader()
            for r in rows:
                w.writerow({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in r.items()})
        print(f"wrote {args.csv}")


if __name__ == "__main__":
    main()
