"""Recovery of the lens-light fit (subslope.physics.light.fit) on simulated lenses.

Renders ``--n`` train-scene lenses with the ``hst_joint`` lens-light prior on the sky
level of the reduced config (Sérsic source of 20.5-23 mag, as the reduced config
renormalises its COSMOS sources; no subhalos or line-of-sight halos; empirical F814W PSF;
detector noise of the reduced config), fits their lens light and sky pedestal with the
arcs masked exactly as the HST lenses are fitted, and prints the median and the 16-84%
range of the errors of mag, R_sersic, n, q and the sky level, and the time.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/lens_light_fit.py --n 200
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/lens_light_fit.py --n 200 \
        --dtype float32 --iterations 6

``--dtype`` and ``--iterations`` are the fit's knobs (model precision, LM steps per pass).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from subslope import config as cfgmod
from subslope.physics.instrument import add_noise
from subslope.physics.light.fit import fit_lens_light
from subslope.physics.light.sersic import e1e2_to_q_phi
from subslope.render.pipeline import RenderSettings, render
from subslope.simulation.macro import sample_macro
from subslope.simulation.observing import build_instrument, build_psf
from subslope.simulation.scenes import Scene


def simulated_fit(n: int, seed: int, resources: str, **fit_kw):
    """``(truth, fit, seconds)`` for ``n`` simulated lenses (module docstring); ``fit_kw``
    go to :func:`fit_lens_light`."""
    cfg = cfgmod.validate({"data": {"resources_dir": resources}})
    scene = Scene.from_config(
        "train",
        {
            "lens_light": {"prior": "hst_joint"},
            "source": {"kind": "sersic", "mag": {"dist": "uniform", "low": 20.5, "high": 23.0}},
            "components": {"subhalos": False, "los": False, "sky": True},
            "sky": {"level": {"dist": "normal", "mean": 0.0661, "std": 0.0813, "low": 0.0}},
        },
    )
    macro = sample_macro(scene, n, np.random.default_rng(seed))
    psf = build_psf(cfg)
    inst = build_instrument(cfg)
    settings = RenderSettings(device="cpu", dtype=torch.float64, compile="off")
    clean = render(macro, torch.as_tensor(psf), settings)
    images = add_noise(clean, seed, instrument=inst).numpy()
    t = time.perf_counter()
    fit = fit_lens_light(
        images,
        psf,
        np.stack([macro["lens_x"], macro["lens_y"]], 1),
        macro["theta_e"],
        background_sigma=inst.background_sigma,
        exposure_time=inst.total_exposure_time,
        pixel_scale=settings.pixel_scale,
        **fit_kw,
    )
    q, _ = e1e2_to_q_phi(torch.as_tensor(macro["light_e1"]), torch.as_tensor(macro["light_e2"]))
    truth = {
        "mag": macro["light_mag"],
        "r_sersic": macro["light_r"],
        "n_sersic": macro["light_n"],
        "q": q.numpy(),
        "sky": macro["sky_level"],
    }
    return truth, fit, time.perf_counter() - t


def errors(truth, fit) -> dict[str, np.ndarray]:
    """Errors: Δmag, ΔR/R, Δn, Δq, Δsky (e⁻/s per pixel)."""
    return {
        "mag": fit.mag - truth["mag"],
        "r_sersic": fit.r_sersic / truth["r_sersic"] - 1.0,
        "n_sersic": fit.n_sersic - truth["n_sersic"],
        "q": fit.q - truth["q"],
        "sky": fit.background - truth["sky"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--resources", default="../shared/data")
    ap.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    ap.add_argument("--iterations", type=int, default=10)
    args = ap.parse_args()
    torch.set_num_threads(1)
    truth, fit, seconds = simulated_fit(
        args.n,
        args.seed,
        args.resources,
        dtype=getattr(torch, args.dtype),
        iterations=args.iterations,
    )
    print(f"{args.n} lenses fitted in {seconds:.1f} s ({1e3 * seconds / args.n:.0f} ms each)")
    print("| quantity | median error | 16-84% | median abs |\n|---|---|---|---|")
    for key, err in errors(truth, fit).items():
        lo, med, hi = np.percentile(err, [16, 50, 84])
        print(f"| {key} | {med:+.3f} | [{lo:+.3f}, {hi:+.3f}] | {np.median(np.abs(err)):.3f} |")


if __name__ == "__main__":
    main()
