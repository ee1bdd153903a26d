#!/usr/bin/env bash
# The renderer's throughput goals (docs/performance.md, "Batched rendering"), measured in one
# run, one benchmark at a time, so that every number of the goal table comes from the same
# machine state. Run it alone on the machine (a quiet machine: nothing else on its cores).
#
#   bash benchmarks/batching_goals.sh [OUT_DIR]      # default results/benchmarks/goals
#
# Writes one log per benchmark and goals.md (the logs' tables, with the machine and the
# load before and after each). About 15 minutes on the 2-core development machine.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-results/benchmarks/goals}
mkdir -p "$out"
py=.venv/bin/python
export OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1
export SUBSLOPE_DATA_MIRROR=${SUBSLOPE_DATA_MIRROR:-../shared/data}

run() {  # name, command...
    local name=$1
    shift
    echo "== $name: load $(cut -d' ' -f1-3 /proc/loadavg)" | tee -a "$out/goals.md"
    "$@" 2>&1 | tee "$out/$name.log" | grep -E '^\||render-only' >>"$out/goals.md" || true
    echo "   load after: $(cut -d' ' -f1-3 /proc/loadavg)" | tee -a "$out/goals.md"
}

{
    echo "# Throughput goals, $(date -u +%Y-%m-%dT%H:%MZ), commit $(git rev-parse --short HEAD)"
    echo "CPU: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(nproc --all) cores"
} >"$out/goals.md"
run end_to_end $py benchmarks/simulate_end_to_end.py --images 64 --repeats 5 --lenstronomy 4
run vs_lenstronomy $py benchmarks/simulate_vs_lenstronomy.py --n-img 8 --repeats 3 --no-ref64 \
    --scenes 'train:0:0,train:0:1,train:1500:1,nfw:1500:1,tnfw:1500:1' \
    --csv "$out/vs_lenstronomy.csv"
run stream $py benchmarks/stream_throughput.py --batch 32 --batches 6 --repeats 3
run compile_cache $py benchmarks/compile_cache.py --images 20 --warm 2
echo "wrote $out/goals.md"
