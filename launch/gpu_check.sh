#!/usr/bin/env bash
# The first minutes on a GPU (README, "Before your first cluster week"): times and loads the paper scale on the
# one GPU of this machine, 10-15 minutes on an H200, unattended; figures in outputs/gpu_check/gpu_check.json.
# Usage: launch/gpu_check.sh [--out DIR] [--fit-iterations N] [Hydra overrides, e.g. paths.weights_dir=/data/weights]
set -euo pipefail
cd "$(dirname "$0")/.."
exec "${PYTHON:-.venv/bin/python}" benchmarks/gpu_check.py "$@"
