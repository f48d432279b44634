"""SLURM jobs sized and timed from measured figures: the requeue signal's lead time, each job kind's memory and CPUs,
and the shard count that keeps every shard inside the time limit.

The lead time: SLURM signals the job ``lead`` seconds before its limit; the requeue waits for the step in flight
(``tracegs.training.checkpoints.CheckpointOnSignal``), saves and calls ``scontrol requeue``. So the lead must cover
one whole iteration (measured, with a margin for a slower node), the checkpoint's save and the requeue call;
a shorter one is killed before it saves and loses every step since the last periodic checkpoint.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

from tracegs.errors import ConfigError, InputFileError

# Assumed, not measured: an hpc checkpoint holds the LoRA factors and their AdamW state (float32) and the trainer's
# state, ~0.8 GB at paper scale; 60 s covers a shared file system at >= 15 MB/s.
SAVE_SECONDS = 60.0
STEP_MARGIN = 1.25  # an iteration may run 25% slower than measured (a busier node, the first steps after resume)
REQUEUE_SECONDS = 30.0  # signal delivery and ``scontrol requeue``
SHARD_FILL = 0.8  # a shard plans for 80% of its time limit: the unit-time estimate is an order of magnitude


def signal_lead_seconds(step_seconds: float, save_seconds: float = SAVE_SECONDS) -> int:
    """The requeue signal's lead before the time limit that one iteration plus a save fits in."""
    return math.ceil(step_seconds * STEP_MARGIN + save_seconds + REQUEUE_SECONDS)


def require_lead(signal_delay_s: float, step_seconds: float, origin: str, field: str) -> None:
    """Refuse a lead time that one iteration (``origin`` says where its seconds come from) cannot finish in."""
    needed = signal_lead_seconds(step_seconds)
    if signal_delay_s < needed:
        raise ConfigError(field, f"{signal_delay_s:g} s before the limit is too short for one iteration "
                                 f"({step_seconds:.0f} s, {origin}) x {STEP_MARGIN} + a checkpoint save "
                                 f"({SAVE_SECONDS:.0f} s, assumed) + requeue ({REQUEUE_SECONDS:.0f} s): the job would "
                                 f"be killed before it saves; set it to at least {needed}")


def measured_iteration(gpu_check: str | Path) -> tuple[float, str]:
    """(seconds of one Stage-2 iteration, where from) in a GPU check's JSON (benchmarks/gpu_check.py)."""
    try:
        record = json.loads(Path(gpu_check).read_text())
        seconds = float(record["stage2"]["iteration"]["seconds"])
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise InputFileError(gpu_check, f"no stage2.iteration.seconds ({type(error).__name__})",
                             "run launch/gpu_check.sh on the cluster's GPU and point at its gpu_check.json") \
            from error
    device = record.get("device", {}).get("name", "unknown device")
    return seconds, f"measured on {device}, {Path(gpu_check).name}"


@dataclass(frozen=True)
class JobKind:
    """Host memory and CPUs of one task of a job kind: the measured resident set of the process without its
    models, plus the host-resident bytes of the models it loads at paper scale, times a margin."""

    name: str
    models_gb: float  # host-resident model bytes at paper scale (declared: the released files' dtypes)
    models_origin: str
    cpus: int
    cpus_origin: str


# The process without its models: the peak RSS of the embedded demo (every command of the pipeline, tiny models),
# measured on a clean clone (docs/clean_clone.md: 1.06 GiB, AMD EPYC, 2 cores).
BASE_RSS_GB = 1.06 * 2**30 / 1e9
MEMORY_MARGIN = 1.5  # loaders hold a second copy of a shard while they cast it; data in flight

# Host-resident bytes of the released models, in the dtype each is loaded in (backbone.*.dtype at paper scale).
TRANSFORMER_GB = 11.2  # GSFixer's CogVideoX-5B transformer, bf16 (5.6 B parameters)
ENCODERS_GB = 9.5 + 2.5 + 0.6 + 0.4  # T5-XXL bf16, VGGT-1B bf16, DINOv2-L bf16, the CogVideoX VAE bf16
BLIP2_GB = 7.7  # BLIP-2 OPT-2.7B, fp16
FRAMES_GB = 3.4  # one DL3DV scene's frames in float32 while its 3DGS is fitted (300 x 540 x 960 x 3 x 4 B: assumed)

JOB_KINDS = {
    "prepare": JobKind("prepare", TRANSFORMER_GB + ENCODERS_GB + BLIP2_GB + FRAMES_GB,
                       "restorer + T5/VGGT/DINOv2/VAE + BLIP-2 + one scene's frames", 4,
                       "assumed: 3DGS fits and encoders run on the GPU; the CPU reads images and writes shards"),
    "evaluate": JobKind("evaluate", TRANSFORMER_GB + ENCODERS_GB + BLIP2_GB + FRAMES_GB,
                        "restorer + T5/VGGT/DINOv2/VAE + BLIP-2 + one scene's frames", 4,
                        "as prepare: deployment's fits and restorations run on the GPU"),
    "train": JobKind("train", TRANSFORMER_GB, "the restorer (ranks read cached latents and tokens)", 8,
                     "assumed: the rank's intra-op threads (the loader runs in-process, num_workers 0)"),
    "report": JobKind("report", TRANSFORMER_GB + ENCODERS_GB, "restorer + encoders (Fig. 6 rollouts)", 4,
                      "as evaluate"),
}


def memory_gb(kind: str, tasks: int = 1) -> int:
    """``--mem`` in GB for ``tasks`` tasks of ``kind`` on one node."""
    job = JOB_KINDS[kind]
    return math.ceil(tasks * (BASE_RSS_GB + job.models_gb) * MEMORY_MARGIN)


def shard_count(units: int, unit_seconds: float, time_limit_s: float, field: str = "--time-limit-h") -> int:
    """Shards of ``units`` (scenes) so that none exceeds ``SHARD_FILL`` of the time limit (``field``) at
    ``unit_seconds``."""
    per_shard = math.floor(time_limit_s * SHARD_FILL / unit_seconds)
    if per_shard < 1:
        raise ConfigError(field, f"one unit takes {unit_seconds / 3600:.1f} h, more than "
                                 f"{SHARD_FILL:.0%} of the {time_limit_s / 3600:.0f} h limit: no shard fits")
    return math.ceil(units / per_shard)
