"""benchmarks/stage2_memory.py: one Stage-2 step per memory mode at the paper's shapes (GPU) or the rehearsal's."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import stage2_memory  # noqa: E402  (a script directory, not a package)

from tracegs.restorer.memory import training_component_bytes  # noqa: E402


def test_paper_component_bytes_on_the_meta_device():
    backbone = stage2_memory.compose_experiment("paper")[0]
    sizes = training_component_bytes(backbone)
    assert sizes["adapter_params"] == 66_060_288  # supplement: 66.06 M-parameter adapters (rank 32)
    assert sizes["student_adapter"] == 4 * sizes["adapter_params"]  # float32 factors on the bf16 base
    assert sizes["adamw_state"] == 2 * sizes["student_adapter"]


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_paper_shape_step_fits_and_stepwise_needs_less():
    summary = stage2_memory.main(["--scale", "paper"])
    assert summary["peak_mib"]["stepwise"] < summary["peak_mib"]["retain"]


@pytest.mark.slow
def test_rehearsal_step_trains_from_a_stage1_adapter_made_on_its_base():
    """The CPU measurement end to end: the adapter it writes must pass Stage 2's stage/base/dtype check."""
    summary = stage2_memory.main(["--scale", "rehearsal", "--rollout", "2", "--batch", "1"])
    assert summary["scale"] == "rehearsal"
    assert set(summary["peak_mib"]) == set(summary["peak_mib_guidance_before"]) == {"retain", "stepwise"}
    assert all(value > 0 for value in summary["peak_mib"].values())
