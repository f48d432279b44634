#!/usr/bin/env bash
# The Table 3 ablation grid as Hydra multiruns, locally or on SLURM through the submitit launcher.
#
# Usage:   launch/sweep_ablation.sh [local|slurm] [extra Hydra overrides, e.g. experiment=paper]
# Order:   baseline (A) -> one shared Stage-1 adapter -> Stage 2 for B..F (one job each, all loading
#          the same Stage-1 checkpoint) -> evaluation of A..F -> Table 3 -> Fig. 6 (A, off-policy E,
#          on-policy F along their reverse trajectories on held-out clips; synthetic benchmark only).
# SLURM:   hydra/launcher=slurm takes nodes / tasks_per_node / gpus_per_node from the trainer
#          group, so `trainer=ddp trainer.devices=4` sizes every job of the sweep.
set -euo pipefail
cd "$(dirname "$0")/.."
where="${1:-local}"; shift || true
launcher="hydra/launcher=${where}"
BIN=.venv/bin
"$BIN/tracegs-train" stage=baseline "$@"
"$BIN/tracegs-train" stage=stage1 "$@"
"$BIN/tracegs-train" -m "$launcher" stage=stage2 ablation=B,C,D,E,F-,F "$@"
# Each variant is scored by the method that stands for it (A: baseline restorer, B..F: their student).
"$BIN/tracegs-evaluate" -m "$launcher" ablation=A,B,C,D,E,F-,F 'evaluation.methods=[${ablation.method}]' "$@"
"$BIN/tracegs-report" report.kind=ablation "$@"
# Held-out clips with ground truth exist for the embedded synthetic benchmark only.
if [[ " $* " != *"experiment="* && " $* " != *"data="* ]]; then
  "$BIN/tracegs-prepare" data.prepare.split=test "$@"
  "$BIN/tracegs-report" report.kind=per_step data.prepare.split=test \
    'evaluation.held_out_cache=${data.prepare.cache_dir}' "$@"
fi
