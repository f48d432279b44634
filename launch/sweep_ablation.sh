#!/usr/bin/env bash
# The Table 3 ablation grid as Hydra multiruns, locally or on SLURM through the submitit launcher.
#
# Usage:   launch/sweep_ablation.sh [local|slurm] [extra Hydra overrides, e.g. experiment=paper]
# Order:   (embedded scale: prepare) -> baseline (A) -> one shared Stage-1 adapter -> Stage 2 for B..F
#          (one job each, all loading the same Stage-1 checkpoint) -> evaluation of A..F -> Table 3 ->
#          Fig. 6 (A, off-policy E, on-policy F along their reverse trajectories on held-out clips;
#          synthetic benchmark only).
# SLURM:   hydra/launcher=slurm sizes each job from the trainer group: `trainer=ddp trainer.devices=4` gives
#          training jobs four ranks on four GPUs, and every other step one process on one GPU; CPUs,
#          memory and time come from trainer.cluster. Every step, including the report, runs on compute nodes.
set -euo pipefail
cd "$(dirname "$0")/.."
where="${1:-local}"; shift || true
launcher="hydra/launcher=${where}"
BIN=.venv/bin
# Every step is a multirun through the chosen launcher, so on SLURM each one runs on compute nodes (the
# submitit launcher waits for its jobs) and this script only submits; locally it runs in this process.
# A SLURM array carries one name: the swept steps name themselves after all their variants (job_name).
step() { "$BIN/$1" -m "$launcher" "${@:2}"; }
# The embedded benchmark prepares only the all-view teacher by default; variants C and D need 12 and 18, and
# B the sparse fits' final snapshots, so the sweep prepares its own cache with them (resumed when there).
embedded=false
if [[ " $* " != *"experiment="* && " $* " != *"data="* ]]; then
  embedded=true
  set -- 'data.prepare.dense_views=[12,18,null]' 'data.prepare.student_final_fits=true' "$@"
  step tracegs-prepare "$@"
fi
# The variants are the files of conf/ablation/ in their Table 3 rows; those that train a student get Stage 2.
variants=$("$BIN/python" -m tracegs.pipeline.variants)
trained=$("$BIN/python" -m tracegs.pipeline.variants --trained)
step tracegs-train stage=baseline "$@"
step tracegs-train stage=stage1 "$@"
step tracegs-train stage=stage2 "ablation=$trained" "job_name=train-stage2-${trained%%,*}-${trained##*,}" "$@"
# Each variant is scored by the method that stands for it (the frozen baseline restorer or its student).
step tracegs-evaluate "ablation=$variants" 'evaluation.methods=[${ablation.method}]' \
  "job_name=evaluate-${variants%%,*}-${variants##*,}" "$@"
step tracegs-report report.kind=ablation "$@"
# Held-out clips with ground truth exist for the embedded synthetic benchmark only.
if $embedded; then
  step tracegs-prepare data.prepare.split=test "$@"
  step tracegs-report report.kind=per_step data.prepare.split=test \
    'evaluation.held_out_cache=${data.prepare.cache_dir}' "$@"
fi
