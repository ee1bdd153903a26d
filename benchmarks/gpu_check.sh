#!/usr/bin/env bash
# One prepared check on a machine with a CUDA GPU (<= 8 minutes on one H100/H200):
#   1. the `gpu`-marked tests (pytest -m gpu);
#   2. render throughput of the batched renderer (batching 'auto', batch_images = the
#      batch) at the mean training scene (N_sub = 1500 + LoS) for batch sizes 64-1024,
#      float32, with each batch's error against the CPU float64 reference and its peak
#      GPU memory; ResNet-50 training steps at batch 1000 in fp32, bf16, bf16 +
#      channels_last and bf16 + channels_last + torch.compile; the paper-scale GPU-hours
#      at the fastest rate (benchmarks/gpu_throughput.py);
#   3. training images/s from shards and from the live stream (training.data: stream),
#      rendering on the GPU in the training process and in 2 spawned workers
#      (benchmarks/stream_throughput.py);
# written to OUT_DIR (default $OUT, else results/gpu_check): gpu_tests.log,
# gpu_throughput.md and stream_throughput.md (the tables) and gpu_check.log.
#
#   bash benchmarks/gpu_check.sh [OUT_DIR]
#
# It uses the machine's python3 (PYTHON overrides) with this checkout's src/ on the path.
# Packages that python3 lacks can come as wheels in .whl/ (installed to /tmp/site first),
# e.g. prepared on a machine with network access:
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 \
#     --platform manylinux2014_x86_64 -d .whl astropy pyerfa astropy-iers-data colossus \
#     jsonschema jsonschema-specifications referencing rpds-py pooch platformdirs
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
out="${1:-${OUT:-results/gpu_check}}"
mkdir -p "$out"
py="${PYTHON:-python3}"
if compgen -G ".whl/*.whl" > /dev/null; then
  "$py" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl && export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
{
  date
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv || true
  "$py" -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"
  echo "== gpu tests"
  timeout 150 "$py" -m pytest -q -m gpu -p no:cacheprovider tests 2>&1 | tee "$out/gpu_tests.log" | tail -5
  echo "== throughput"
  timeout 230 "$py" benchmarks/gpu_throughput.py --device cuda --out "$out/gpu_throughput.md"
  echo "== stream"
  timeout 90 "$py" benchmarks/stream_throughput.py --device cuda --batch 256 --batches 4 \
    --batch-images 256 --repeats 2 --workers 0 2 --data "${SUBSLOPE_DATA_MIRROR:-../shared/data}" \
    --out "$out/stream_throughput.md"
  date
} 2>&1 | tee "$out/gpu_check.log"
