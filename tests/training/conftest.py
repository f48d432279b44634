"""Fixtures of the training tests (helpers live in support/training.py)."""

import pytest
import torch
from support.training import TINY_LORA, make_transformer

from tracegs.restorer.adapters import adapter_parameters, add_adapter, save_adapter


@pytest.fixture
def stage1_adapter(tmp_path):
    """A Stage-1 adapter file with non-zero B factors, so teacher and student outputs depend on it."""
    transformer = make_transformer()
    add_adapter(transformer, "aligned", TINY_LORA)
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for p in adapter_parameters(transformer, "aligned"):
            p.copy_(0.2 * torch.randn(p.shape, generator=g))
    path = tmp_path / "stage1_adapter.safetensors"
    save_adapter(transformer, "aligned", path, stage="stage1")
    return path
