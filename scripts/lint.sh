#!/usr/bin/env bash
# The static checks CI runs before the tests (needs the `lint` extra of setup_env.sh):
# ruff (lint and format), snakefmt on the workflow, mypy on the pure-math rooms.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
.venv/bin/ruff check .
.venv/bin/ruff format --check .
.venv/bin/snakefmt --check Snakefile workflow/rules
.venv/bin/mypy
echo "lint: ruff, snakefmt and mypy clean"
