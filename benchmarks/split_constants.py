"""Measure the error constants C_p(ρ) of the near/far population split and write the
data file the renderer reads (``src/subslope/render/split_constants.json``).

The measurement is :mod:`subslope.validation.split_constants`: for every class of
members (EPL γ classes, NFW, tNFW), interior and edge placement, and interpolation
order 4, 6, 8, the worst far-field interpolation error over random members, relative
to the member's largest |α| on r = r_c, times ``--safety``; the elementwise maximum
over ``--seeds``, rounded to 2 significant digits.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/split_constants.py \\
        --members 40 --seeds 0 1 --out src/subslope/render/split_constants.json

Without ``--out`` it prints the tables only. The file records the script, its
arguments, the seeds and the commit it was measured at.
"""

from __future__ import annotations

import argparse
import subprocess
from pathlib import Path

import torch

from subslope.io.atomic import write_json
from subslope.render import nearfar
from subslope.validation.split_constants import measure_tables


def _commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
            cwd=Path(__file__).parent,
        )
        return out.stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--members", type=int, default=40, help="random members per class")
    ap.add_argument("--spacing", type=int, default=3, help="node spacing in grid steps")
    ap.add_argument(
        "--grid", type=int, default=100, help="grid points per side of the edge case (the image)"
    )
    ap.add_argument("--safety", type=float, default=2.0, help="factor on the worst measured ratio")
    ap.add_argument(
        "--seeds", type=int, nargs="+", default=[0, 1], help="elementwise maximum over these seeds"
    )
    ap.add_argument("--out", type=Path, help="write the data file here")
    args = ap.parse_args()
    torch.set_num_threads(1)
    settings = dict(
        members=args.members,
        spacing=args.spacing,
        grid=args.grid,
        safety=args.safety,
        rho_ladder=nearfar.RHO_LADDER,
        gamma_edges=nearfar.EPL_GAMMA_EDGES,
    )
    tables = measure_tables(seeds=args.seeds, **settings)
    for where, by_profile in tables.items():
        print(f"\n{where} ({args.members} members per class, spacing {args.spacing})")
        print(
            "| profile | order | row | " + " | ".join(f"ρ={r:g}" for r in nearfar.RHO_LADDER) + " |"
        )
        print("|---|---|---|" + "---|" * len(nearfar.RHO_LADDER))
        for profile, by_order in by_profile.items():
            for order, rows in by_order.items():
                for i, row in enumerate(rows):
                    print(
                        f"| {profile} | {order} | {i} | "
                        + " | ".join(f"{v:.2g}" for v in row)
                        + " |"
                    )
    if args.out:
        doc = {
            "description": "C_p(rho): bound on the far-field interpolation error of one member "
            "of the near/far "
            "split divided by its largest |alpha| on r = r_c, on rho_ladder; per placement "
            "(interior, edge), profile, interpolation order and class (EPL: gamma classes of "
            "epl_gamma_edges).",
            "provenance": {
                "script": "benchmarks/split_constants.py",
                "seeds": list(args.seeds),
                "members": args.members,
                "spacing": args.spacing,
                "grid": args.grid,
                "safety": args.safety,
                "round_digits": 2,
                "commit": _commit(),
            },
            "rho_ladder": list(nearfar.RHO_LADDER),
            "epl_gamma_edges": list(nearfar.EPL_GAMMA_EDGES),
            **tables,
        }
        write_json(args.out, doc)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
