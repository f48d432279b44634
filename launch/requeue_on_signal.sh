#!/usr/bin/env bash
# Runs a command as a SLURM batch job and requeues the job when SLURM signals the batch shell ahead of the time
# limit (sbatch --requeue --signal=B:USR2@<lead>): prepare and evaluate shards rerun the same command, which skips
# the scenes it finished, so the lead only has to cover the scontrol call.
# Usage: sbatch --requeue --signal=B:USR2@120 ... --wrap "launch/requeue_on_signal.sh tracegs-prepare ..."
set -uo pipefail
"$@" &
child=$!
trap 'scontrol requeue "$SLURM_JOB_ID"' USR2
while :; do
  wait "$child"; status=$?
  kill -0 "$child" 2>/dev/null || exit "$status"  # a trapped signal interrupts wait: wait again while it runs
done
