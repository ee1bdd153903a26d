#!/usr/bin/env bash
# Create or refresh the project virtual environment .venv (idempotent: a second run
# with nothing changed returns in about a second).
#
#   bash scripts/setup_env.sh
#
# Environment knobs:
#   PYTHON           interpreter used to create the venv (default python3, needs >= 3.11)
#   TORCH_INDEX_URL  wheel index for torch (default: pip's configured indexes; on a
#                    machine without a local torch wheel plain PyPI gives a CUDA build,
#                    so for CPU-only use https://download.pytorch.org/whl/cpu)
#   SUBSLOPE_EXTRAS  optional dependency groups to install (default test,lint,reference,slurm)
set -euo pipefail

cd "$(dirname "${BASH_SOURCE[0]}")/.."

PYTHON=${PYTHON:-python3}
VENV=.venv
TORCH_VERSION=2.13.0
TORCH_INDEX_URL=${TORCH_INDEX_URL:-}
EXTRAS=${SUBSLOPE_EXTRAS:-test,lint,reference,slurm}
PY="$VENV/bin/python"

torch_ok() {
    "$PY" -c "import sys, torch; sys.exit(torch.__version__.split('+')[0] != '$TORCH_VERSION')" 2>/dev/null
}

# The stamp records what was installed: it changes with pyproject.toml, the extras and
# the torch pin, so editing any of them triggers a reinstall.
stamp_key=$({ cat pyproject.toml; echo "extras=$EXTRAS torch=$TORCH_VERSION"; } | sha256sum | cut -c1-16)
stamp="$VENV/.subslope-setup-$stamp_key"

if [ -f "$stamp" ] && torch_ok && "$PY" -c "import subslope" 2>/dev/null; then
    echo "setup_env: $VENV is up to date"
    exit 0
fi

if [ ! -x "$PY" ]; then
    "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))' \
        || { echo "setup_env: $PYTHON is older than Python 3.11" >&2; exit 1; }
    echo "setup_env: creating $VENV with $("$PYTHON" --version)"
    "$PYTHON" -m venv "$VENV"
fi

# torch first and pinned, so that pip never resolves a newer one for us.
if ! torch_ok; then
    echo "setup_env: installing torch==$TORCH_VERSION${TORCH_INDEX_URL:+ from $TORCH_INDEX_URL}"
    "$PY" -m pip install "torch==$TORCH_VERSION" ${TORCH_INDEX_URL:+--index-url "$TORCH_INDEX_URL"}
fi

# The package (editable) with its extras; the constraint keeps the torch pin.
constraints=$(mktemp)
trap 'rm -f "$constraints"' EXIT
echo "torch==$TORCH_VERSION" > "$constraints"
echo "setup_env: installing subslope (editable) with extras [$EXTRAS]"
"$PY" -m pip install --quiet -c "$constraints" -e ".[$EXTRAS]"

torch_ok || { echo "setup_env: torch is not $TORCH_VERSION after install" >&2; exit 1; }
rm -f "$VENV"/.subslope-setup-*
touch "$stamp"
echo "setup_env: done ($VENV)"
