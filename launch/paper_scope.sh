#!/usr/bin/env bash
# The paper's scope on SLURM as one chain of dependent jobs (GPU check with the real weights, one timed prepare
# shard, the sharded F-only prepare, Stage 1, Stage 2 under DDP on 4 GPUs, Tables 1/2 and Fig. 6), each sized and
# timed from the GPU check's measured figures (benchmarks/paper_scope.py); each job requeues and resumes.
# Usage: launch/paper_scope.sh --partition P --account A [--dry-run] [--weights-dir DIR] [--gpu-factor 2.5] ...
set -euo pipefail
cd "$(dirname "$0")/.."
exec "${PYTHON:-.venv/bin/python}" benchmarks/paper_scope.py "$@"
