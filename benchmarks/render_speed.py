"""Speed and accuracy of the batched renderer (subslope.render.pipeline) on the `train` scene.

Renders train-scene images (parameters from subslope.simulation.macro.sample_macro, subhalos from
subslope.simulation.subhalos.sample_subhalos with a fixed N_sub, optional DG19 line-of-sight EPL
halos) at N_sub in {0, 1500, 3000} x LoS off/on, one CPU thread by default, and prints
the median wall time per image over `--repeats` repeats, plus the error of the default
settings against a float64, n_terms = 30 reference render of the same parameters
(max |Δ| in units of the per-pixel noise σ, and relative L2).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/render_speed.py [--source sersic|cosmos]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

import numpy as np
import torch

from subslope.physics.cosmology import epl_amp_from_m200
from subslope.physics.instrument import gaussian_psf, load_empirical_psf, noise_sigma_map
from subslope.render import pipeline as R
from subslope.simulation import los_halos as los_mod
from subslope.simulation import scenes
from subslope.simulation import subhalos as S
from subslope.simulation.macro import sample_macro
from subslope.validation.scenes import image_errors

SHARED = Path(os.environ.get("SUBSLOPE_SHARED", "/work/shared")) / "data"


def psf_kernel() -> torch.Tensor:
    path = SHARED / "psf" / "emp_psf_f814w.fits"
    if path.is_file():
        return torch.as_tensor(load_empirical_psf(path))
    return torch.as_tensor(gaussian_psf(0.1, 0.04))


def cosmos_sources(macro: dict, rng: np.random.Generator) -> R.PixelatedSources | None:
    """Random galaxies of the local COSMOS sample placed at each z_source (docs/simulation.md)."""
    from subslope.io.cosmos import CosmosCatalog, place_at_redshift
    from subslope.physics.light.pixelated import pad_stamps

    cat = CosmosCatalog.load(SHARED / "cosmos")
    t = cat.table
    stamps, scales = [], []
    for zs in macro["z_source"]:
        row = t.iloc[int(rng.integers(len(t)))]
        sb, ps = place_at_redshift(
            cat.stamp(int(row["ident"])), float(row["pixel_scale"]), float(row["zphot"]), float(zs)
        )
        stamps.append(sb)
        scales.append(ps)
    st, off = pad_stamps(stamps, dtype=torch.float64)
    return R.PixelatedSources(stamps=st, pixel_scale=np.asarray(scales), offsets=off)


def los_population(scene, macro: dict, rng: np.random.Generator) -> los_mod.LosPopulation:
    """EPL LoS population (reduced deflections w.r.t. each z_source) of a macro draw."""
    batch = los_mod.sample_los_batch(
        macro["z_lens"],
        macro["z_source"],
        macro["theta_e"],
        macro["gamma_ml"],
        macro["delta_los"],
        rng,
    )
    spec = scene.subhalos
    gam = S.sample_subhalo_gammas(
        macro["gamma_sub"], batch.counts, rng, spec.gamma_scatter, spec.gamma_bounds
    )
    n = int(batch.counts.sum())
    e1, e2 = rng.uniform(-0.2, 0.2, n), rng.uniform(-0.2, 0.2, n)
    sys = np.repeat(np.arange(len(batch.counts)), batch.counts)
    amp = np.array(
        [
            float(epl_amp_from_m200(m, g, z, macro["z_source"][s]))
            for m, g, z, s in zip(batch.m200, gam, batch.z, sys)
        ]
    )
    return los_mod.LosPopulation(
        profile="epl",
        counts=batch.counts,
        z=batch.z,
        x=batch.x,
        y=batch.y,
        m200=batch.m200,
        amp=amp,
        gamma=gam,
        e1=e1,
        e2=e2,
    )


def make_batch(
    n_img: int,
    n_sub: int,
    with_los: bool,
    seed: int,
    source: str = "sersic",
    delta_los: float | None = None,
):
    """(macro, psf, sources, subhalos, los) of `n_img` train-scene systems with N_sub fixed."""
    over = {"source": {"kind": "sersic"}} if source == "sersic" else {}
    over["components"] = {"los": with_los}
    scene = scenes.Scene.from_config("train", over)
    rng = np.random.default_rng(seed)
    macro = sample_macro(scene, n_img, rng)
    macro["n_sub"][:] = n_sub
    if with_los and delta_los is not None:
        macro["delta_los"][:] = delta_los
    psf = psf_kernel()
    sources = cosmos_sources(macro, rng) if source == "cosmos" else None
    smooth = R.render_smooth(macro, psf, R.RenderSettings(compile="off"), sources=sources)
    subs = S.sample_subhalos(scene, macro, rng, smooth_images=smooth.numpy())
    los = los_population(scene, macro, rng) if with_los else None
    return macro, psf, sources, subs, los


def reference_settings(settings: R.RenderSettings) -> R.RenderSettings:
    """float64, n_terms = n_terms_main = 30, eager, direct population sums; same grid
    and supersampling."""
    return dataclasses.replace(
        settings,
        dtype=torch.float64,
        n_terms=30,
        n_terms_main=30,
        compile="off",
        chunk_members=64,
        population="direct",
    )


def gamma_demo(out_dir: str = "/tmp", seed: int = 3) -> None:
    """docs/simulation.md: N_sub = 1500 EPL subhalos on the arc at γ = 2.5 vs γ = 1.2.

    Same macro draw (Sérsic source, no lens light, no LoS) for both; prints the flux in
    the arc mask (smooth model > 1/5 of its maximum) relative to the smooth model and the
    flux of the central 5×5 pixels around the lens centre; saves PNGs to ``out_dir``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scene = scenes.Scene.from_config(
        "train", {"source": {"kind": "sersic"}, "components": {"los": False, "lens_light": False}}
    )
    rng = np.random.default_rng(seed)
    macro = sample_macro(scene, 1, rng)
    macro["n_sub"][:] = 1500
    psf = psf_kernel()
    settings = R.RenderSettings(device="cpu")
    smooth = R.render_smooth(macro, psf, settings)[0]
    arc = smooth > 0.2 * smooth.max()
    n = settings.npix
    jc = int(round(macro["lens_y"][0] / settings.pixel_scale + (n - 1) / 2))
    ic = int(round(macro["lens_x"][0] / settings.pixel_scale + (n - 1) / 2))
    centre = (slice(jc - 2, jc + 3), slice(ic - 2, ic + 3))
    print(
        f"smooth: arc flux {float(smooth[arc].sum()):.3f} e-/s, central 5x5 "
        f"{float(smooth[centre].sum()):.4f} e-/s,"
        f" background σ {noise_sigma_map(torch.zeros(1))[0]:.4f} e-/s/pixel"
    )
    imgs = {"smooth": smooth}
    for gam in (2.5, 1.2):
        m = dict(macro, gamma_sub=np.array([gam]))
        subs = S.sample_subhalos(
            scene, m, np.random.default_rng(seed + 1), smooth_images=smooth[None].numpy()
        )
        img = R.render(m, psf, settings, subhalos=subs)[0]
        imgs[f"gamma {gam}"] = img
        dev = float((img - smooth).abs().max() / noise_sigma_map(smooth).max())
        print(
            f"γ = {gam}: arc flux / smooth = {float(img[arc].sum() / smooth[arc].sum()):.3f}, "
            f"central 5x5 {float(img[centre].sum()):.4f} e-/s (smooth "
            f"{float(smooth[centre].sum()):.4f}), "
            f"peak {float(img.max()):.3f} (smooth {float(smooth.max()):.3f}), max |Δ| {dev:.1f} "
            "σ_max, "
            f"total flux / smooth {float(img.sum() / smooth.sum()):.3f}"
        )
    fig, axes = plt.subplots(1, 3, figsize=(12, 4))
    vmax = float(max(v.max() for v in imgs.values()))
    for ax, (name, img) in zip(axes, imgs.items()):
        ax.imshow(img.numpy(), origin="lower", cmap="magma", vmin=0, vmax=vmax)
        ax.contour(arc.numpy(), levels=[0.5], colors="cyan", linewidths=0.5)
        ax.set_title(name)
    fig.savefig(f"{out_dir}/render_gamma_demo.png", dpi=90, bbox_inches="tight")
    print(f"saved {out_dir}/render_gamma_demo.png")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n-img", type=int, default=4, help="images per render call")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--n-sub", default="0,1500,3000")
    ap.add_argument("--source", choices=("sersic", "cosmos"), default="sersic")
    ap.add_argument(
        "--delta-los",
        type=float,
        default=None,
        help="fix δ_los (default: drawn from the scene prior U(0, 2))",
    )
    ap.add_argument("--compile", choices=("auto", "on", "off"), default="auto")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--gamma-demo",
        action="store_true",
        help="only render the docs/simulation.md γ = 2.5 vs 1.2 comparison (PNG in /tmp)",
    )
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.gamma_demo:
        gamma_demo(seed=args.seed + 3)
        return
    settings = R.RenderSettings(compile=args.compile, device="cpu")
    ref_settings = reference_settings(settings)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, load {os.getloadavg()}")
    print(
        f"settings: n_terms={settings.n_terms} n_terms_main={settings.n_terms_main} "
        f"chunk={R.chunk_width(settings, settings.npix**2)} compile={settings.compile} "
        f"dtype={settings.dtype}"
    )
    print("| N_sub | LoS | mean LoS halos | s/image (median) | min | max |Δ|/σ | rel L2 |")
    print("|---|---|---|---|---|---|---|")
    for n_sub in (int(v) for v in args.n_sub.split(",")):
        for with_los in (False, True):
            macro, psf, src, subs, los = make_batch(
                args.n_img, n_sub, with_los, args.seed, args.source, args.delta_los
            )
            img = R.render(macro, psf, settings, sources=src, subhalos=subs, los=los)  # warm-up
            ts = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                R.render(macro, psf, settings, sources=src, subhalos=subs, los=los)
                ts.append((time.perf_counter() - t0) / args.n_img)
            ref = R.render(macro, psf, ref_settings, sources=src, subhalos=subs, los=los)
            es, el = image_errors(img, ref)
            nl = float(np.mean(los.counts)) if los is not None else 0.0
            print(
                f"| {n_sub} | {'on' if with_los else 'off'} | {nl:.1f} | {np.median(ts):.4f} | "
                f"{min(ts):.4f} | {es:.2e} | {el:.2e} |",
                flush=True,
            )
    print(f"load after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
