"""Does the estimator respond to CDM subhalos placed where its training subhalos sit?

The training subhalos are placed on the arcs (bright pixels of the smooth model), the
CDM sets' everywhere. This study simulates one shard of a CDM scene of a finished
campaign with its subhalos on the arcs instead (``subhalos.placement: arc``), at one
concentration multiplier, and measures what the campaign measures for the shipped
placement: the paired shift of the stack γ_MLE against the same sets re-rendered without
their subhalos (:mod:`subslope.stages.null_tests.visibility`) and the ideal observer's
Δχ² of the first images (:mod:`subslope.stages.signal_budget`). Run it in the campaign's
folder (its model, thresholds not needed):

    OMP_NUM_THREADS=2 .venv/bin/python studies/placement_response.py --scene nfw \\
        --multiplier 4 --placement arc --out results/placement_response
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import yaml


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--model", default="results/train_estimator/model.pt")
    ap.add_argument("--scene", default="nfw")
    ap.add_argument("--multiplier", type=float, default=4.0)
    ap.add_argument("--placement", choices=("arc", "everywhere"), default="arc")
    ap.add_argument("--shard", type=int, default=0)
    ap.add_argument("--budget-images", type=int, default=16)
    ap.add_argument("--out", type=Path, default=Path("results/placement_response"))
    args = ap.parse_args(argv)

    from subslope.config import load
    from subslope.stages.evaluate import evaluate_shard
    from subslope.stages.null_tests.halo_free import halo_free_shard
    from subslope.stages.null_tests.visibility import paired_stack_mles, visibility_row
    from subslope.stages.signal_budget import budget_rows
    from subslope.stats.intervals import gamma_grid

    args.out.mkdir(parents=True, exist_ok=True)
    overlay = args.out / "overlay.yaml"
    overlay.write_text(
        yaml.safe_dump(
            {
                "base": str(Path(args.config).resolve()),
                "scenes": {args.scene: {"subhalos": {"placement": args.placement}}},
            }
        )
    )
    config = load(overlay)
    tag = f"{args.scene}_a{args.multiplier:g}_{args.placement}"
    shard = args.out / f"{tag}.h5"
    if not shard.exists():
        exe = Path(sys.executable).with_name("subslope")
        subprocess.run(
            [str(exe), "simulate", "--config", str(overlay), "--scene", args.scene,
             "--shard", str(args.shard), "--multiplier", str(args.multiplier), "--out", str(shard)],
            check=True,
        )  # fmt: skip
    grid = config["inference"]["gamma_grid"]
    gammas = gamma_grid(grid["low"], grid["high"], grid["n"])
    original, removed = args.out / f"{tag}_profiles.h5", args.out / f"{tag}_free.h5"
    if not original.exists():
        evaluate_shard(args.model, shard, original, gammas=gammas)
    if not removed.exists():
        halo_free_shard(config, args.model, shard, {"subhalos_removed": removed}, gammas=gammas)
    row = visibility_row(
        args.scene, *paired_stack_mles([original], [removed]), multiplier=args.multiplier
    )
    rows = budget_rows(
        shard,
        args.budget_images,
        mask_factor=config["training"]["mask_factor"],
        scene=args.scene,
        multiplier=args.multiplier,
    )
    refit = sorted(r["dchi2_refit"] for r in rows)
    row["placement"] = args.placement
    row["dchi2_refit_p50"] = refit[len(refit) // 2] if refit else float("nan")
    (args.out / f"{tag}.json").write_text(json.dumps(row, indent=1) + "\n")
    print(json.dumps(row, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
