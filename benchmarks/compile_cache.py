"""First-job overhead of torch.compile with a cold and a warm shared cache.

Runs ``subslope simulate`` (the workflow's shard job) as separate processes on a
``--images``-image training shard (N_sub ~ U{0, 3000} + LoS, compile 'on'), each with
``simulation.render.compile_cache`` pointing at one fresh folder: the first process
compiles into the empty cache, the later ones load from it, as the later jobs of a
campaign do. A last run with compile 'off' gives the eager time of the same images.
Prints the wall time of each process and its render timings.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/compile_cache.py [--images 20] [--warm 2]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


def run(config: Path, out: Path, log: Path) -> tuple[float, dict]:
    exe = Path(sys.executable).with_name("subslope")
    command = [str(exe), "simulate", "--config", str(config), "--scene", "train",
               "--shard", "0", "--out", str(out), "--overwrite", "--quiet"]  # fmt: skip
    t = time.perf_counter()
    proc = subprocess.run(command, capture_output=True, text=True, cwd=ROOT, check=True)
    wall = time.perf_counter() - t
    log.write_text(proc.stdout + proc.stderr)
    found = re.search(r"timings \(s\): (\{[^}]*\})", proc.stdout + proc.stderr)
    timings = json.loads(found.group(1).replace("'", '"')) if found else {}
    return wall, timings


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", type=int, default=20)
    ap.add_argument("--warm", type=int, default=2, help="runs on the warm cache")
    data = Path(os.environ.get("SUBSLOPE_DATA_MIRROR", ROOT / "resources"))
    ap.add_argument(
        "--data", type=Path, default=data,
        help="psf/ and COSMOS folders (default $SUBSLOPE_DATA_MIRROR, else resources/)",
    )  # fmt: skip
    args = ap.parse_args(argv)
    print(f"load {os.getloadavg()}, {os.cpu_count()} cores")
    print("| run | process wall s | setup s | smooth s | render s | total s |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        runs = [("cold cache", "on")] + [(f"warm cache {k + 1}", "on") for k in range(args.warm)]
        for label, compile_mode in [*runs, ("eager (compile off)", "off")]:
            overlay = {
                "base": str(ROOT / "config" / "config.yaml"),
                "data": {"resources_dir": str(args.data)},
                "simulation": {
                    "scenes": {"train": {"n_shards": 1, "images_per_shard": args.images}},
                    "render": {"compile": compile_mode, "compile_cache": str(tmp / "cache")},
                    "shard_cache": None,
                },
            }
            config = tmp / "config.yaml"
            config.write_text(yaml.safe_dump(overlay))
            wall, tm = run(config, tmp / "shard.h5", tmp / f"{label}.log")
            print(
                f"| {label} | {wall:.1f} | {tm.get('setup', 0):.1f} | {tm.get('smooth', 0):.1f}"
                f" | {tm.get('render', 0):.1f} | {tm.get('total', 0):.1f} |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
