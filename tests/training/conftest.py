"""Fixtures of the training tests (helpers live in training_support.py)."""

import pytest
import torch
from training_support import TINY_LORA, make_transformer

from tracegs.restorer.adapters import adapter_parameters, add_adapter, save_adapter


@pytest.fixture(autouse=True)
def single_thread():
    """One intra-op thread: the tiny tensors gain nothing from two, and on a shared 2-core machine
    spinning OpenMP workers slow these tests down by an order of magnitude."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


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
    save_adapter(transformer, "aligned", path)
    return path
