#!/usr/bin/env bash
# The Table 3 ablation grid as Hydra multiruns, locally or on SLURM through the submitit launcher.
#
# Usage:   launch/sweep_ablation.sh [local|slurm] [extra Hydra overrides, e.g. experiment=paper]
# The steps (prepare -> A -> Stage 1 -> Stage 2 of every trained variant -> evaluation of every variant ->
# Table 3 -> Fig. 6) and the variants (conf/ablation/) are declared in tracegs/pipeline/steps.py; each step is
# one multirun through hydra/launcher=<where>, so on SLURM every step runs on compute nodes. Add --dry-run
# after <where> to print the commands only.
set -euo pipefail
cd "$(dirname "$0")/.."
where="${1:-local}"; shift || true
exec .venv/bin/python -m tracegs.pipeline.steps --sweep "$where" "$@"
