#!/usr/bin/env bash
# Single-GPU (or CPU) debug run: a few steps of a stage with the paper-scale code path but tiny
# limits, anomaly detection on, and the resolved config printed first.
#
# Usage:   launch/debug_single_gpu.sh [stage=stage2] [experiment=paper backbone.transformer.pretrained_path=...]
# Without a GPU it falls back to trainer=cpu, so it also works on a laptop.
set -euo pipefail
cd "$(dirname "$0")/.."
if .venv/bin/python -c "import torch,sys; sys.exit(0 if torch.cuda.is_available() else 1)"; then
  trainer=gpu
else
  trainer=cpu
fi
.venv/bin/tracegs-train trainer="$trainer" debug=limit "$@" --cfg job | head -n 60
exec .venv/bin/tracegs-train trainer="$trainer" debug=limit "$@"
