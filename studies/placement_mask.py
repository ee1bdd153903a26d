"""Fraction of the image inside the subhalo placement mask, with and without cleaning the
COSMOS stamps (docs/realism.md, "Sources").

Subhalos of the EPL scenes are placed on the bright pixels of the smooth model (main
lens + source, no lens light): pixels above ``threshold_fraction`` × its maximum. A
stamp that carries its sky noise, renormalised to a bright magnitude, lifts the whole
source plane above that threshold, so the mask covers the field instead of the arc.
This script draws ``--n`` train systems (the reduced config's sources: both catalogue
folders, renormalised to 20.5-22.5 mag), renders their smooth models with the stamps
as they are and cleaned, and prints the distribution of the mask fraction.

    OMP_NUM_THREADS=1 .venv/bin/python studies/placement_mask.py --n 200
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
from subslope.simulation.sources import draw_sources, pixelated_sources


def mask_fractions(config, n: int, seed: int) -> np.ndarray:
    """Placement-mask fraction of ``n`` train systems under ``config``'s sources."""
    sc, _ = resolved_scene(config, "train")
    macro = sample_macro(sc, n, np.random.default_rng(seed))
    zp = float(config["instrument"]["zero_point"])
    sources, stamps, pad = draw_sources(config, sc, macro, np.random.default_rng(seed + 1), zp)
    settings = RenderSettings(device="cpu", dtype=torch.float32, compile="off")
    psf = torch.as_tensor(build_psf(config), dtype=torch.float32)
    src = pixelated_sources(stamps, sources["pixel_scale"], pad, settings)
    smooth = render_smooth(macro, psf, settings, sources=src).numpy()
    peak = smooth.reshape(n, -1).max(1)[:, None, None]
    return (smooth > sc.subhalos.threshold_fraction * peak).mean((1, 2))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--resources", default="../shared/data")
    args = ap.parse_args()
    torch.set_num_threads(1)
    base = cfgmod.load(args.config, env=False)
    base["data"]["resources_dir"] = args.resources
    from subslope.simulation.sources import source_split

    cleaned = cfgmod.validate(copy.deepcopy(base))
    chosen = source_split(cleaned, "train")[1]
    src = base["simulation"]["sources"]
    variants = {
        "previous config: 10 bundled stamps as they are, 19.5-21.5 mag": {
            "folder": "cosmos",
            "clean": {"enabled": False},
            "mag_renormalize": [19.5, 21.5],
        },
        "the cleaned config's galaxies, stamps as they are": {
            "clean": {"enabled": False},
            "split": dict(
                src["split"], ids={"train": chosen.tolist(), "validation": [], "test": []}
            ),
        },
        "this config: cleaned stamps": {},
    }
    print("| sources | train galaxies | mask fraction: median | 16-84% | 95th |")
    print("|---|---|---|---|---|")
    for label, over in variants.items():
        cfg = copy.deepcopy(base)
        for key, value in over.items():
            if isinstance(value, dict) and isinstance(cfg["simulation"]["sources"].get(key), dict):
                cfg["simulation"]["sources"][key].update(value)
            else:
                cfg["simulation"]["sources"][key] = value
        cfg = cfgmod.validate(cfg)
        frac = mask_fractions(cfg, args.n, args.seed)
        lo, med, hi, p95 = np.percentile(frac, [16, 50, 84, 95])
        n_gal = len(source_split(cfg, "train")[1])
        print(f"| {label} | {n_gal} | {med:.3f} | [{lo:.3f}, {hi:.3f}] | {p95:.3f} |")


if __name__ == "__main__":
    main()
