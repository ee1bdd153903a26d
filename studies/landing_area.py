"""Candidate pixels of the reference code's CDM placement against ``placement: landing``
(docs/simulation.md, "Subhalo placement").

The reference code (repository gemyxzhang/neural-subhalo-slope-data, ``utils.py``) put
the subhalos of its figure-4 sets on the pixels where the smooth lensed source (PSF, no
lens light, the COSMOS stamp with its own sky noise) is above 0. Our stamps are cleaned
(the sky outside the galaxy set to zero), so "above 0" on them selects only the galaxy.
This script draws ``--n`` systems of a CDM scene (test sources) and prints, per image,
the fraction of the field selected by

- ``reference``: the same galaxies with their stamps as they are (clean off), > 0;
- ``cleaned > 0``: the cleaned stamps, > 0;
- ``landing``: the image of the stamp's support (:func:`subslope.simulation.sources.
  landing_stamps`) above ``threshold_fraction`` of its maximum (the scene's value);

and how much of the reference's candidate area each rule covers (recall) and how much
of each rule's area the reference selects (precision).

    OMP_NUM_THREADS=1 .venv/bin/python studies/landing_area.py --n 208
"""

from __future__ import annotations

import argparse
import copy

import numpy as np
import torch

from subslope import config as cfgmod
from subslope.render.pipeline import RenderSettings, render_smooth
from subslope.simulation.macro import sample_macro
from subslope.simulation.observing import build_psf
from subslope.simulation.resolve import resolved_scene
from subslope.simulation.sources import (
    draw_sources,
    landing_stamps,
    pixelated_sources,
    source_split,
)


def smooth_images(config, scene: str, n: int, seed: int, landing: bool = False) -> np.ndarray:
    """Smooth models of ``n`` systems of ``scene`` (the same draws for every config)."""
    sc, _ = resolved_scene(config, scene)
    macro = sample_macro(sc, n, np.random.default_rng(seed), multiplier=1.0)
    zp = float(config["instrument"]["zero_point"])
    sources, stamps, pad = draw_sources(config, sc, macro, np.random.default_rng(seed + 1), zp)
    if landing:
        stamps = landing_stamps(stamps)
    settings = RenderSettings(device="cpu", dtype=torch.float64, compile="off")
    psf = torch.as_tensor(build_psf(config), dtype=torch.float64)
    src = pixelated_sources(stamps, sources["pixel_scale"], pad, settings)
    return render_smooth(macro, psf, settings, sources=src).numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, default=208, help="a multiple of 13")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--scene", default="nfw_ref")
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--resources", default="../shared/data")
    args = ap.parse_args()
    torch.set_num_threads(1)
    base = cfgmod.load(args.config, env=False)
    base["data"]["resources_dir"] = args.resources
    cleaned = cfgmod.validate(copy.deepcopy(base))
    sc, _ = resolved_scene(cleaned, args.scene)
    chosen = source_split(cleaned, sc.source.split)[1]
    raw = copy.deepcopy(base)
    raw_src = raw["simulation"]["sources"]
    raw_src["clean"]["enabled"] = False
    raw_src["split"]["ids"] = {
        "train": [],
        "validation": [],
        "test": [],
        sc.source.split: chosen.tolist(),
    }
    raw = cfgmod.validate(raw)

    ref = smooth_images(raw, args.scene, args.n, args.seed) > 0
    peak = lambda im: im.reshape(im.shape[0], -1).max(1)[:, None, None]  # noqa: E731
    clean = smooth_images(cleaned, args.scene, args.n, args.seed)
    land = smooth_images(cleaned, args.scene, args.n, args.seed, landing=True)
    rules = {
        "reference (stamps as they are) > 0": ref,
        "cleaned > 0": clean > 0,
        f"landing > {sc.subhalos.threshold_fraction:g} x max": (
            land > sc.subhalos.threshold_fraction * peak(land)
        ),
    }
    print(f"{args.n} systems of scene {args.scene!r}, {len(chosen)} test galaxies")
    print("| rule | field fraction: median | 16-84% | recall of reference | precision |")
    print("|---|---|---|---|---|")
    for label, mask in rules.items():
        frac = mask.mean((1, 2))
        both = (mask & ref).sum((1, 2))
        recall = both / np.maximum(ref.sum((1, 2)), 1)
        precision = both / np.maximum(mask.sum((1, 2)), 1)
        lo, med, hi = np.percentile(frac, [16, 50, 84])
        print(
            f"| {label} | {med:.3f} | [{lo:.3f}, {hi:.3f}] | {np.median(recall):.2f} | "
            f"{np.median(precision):.2f} |"
        )


if __name__ == "__main__":
    main()
