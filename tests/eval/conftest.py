"""Deployment tests run tiny tensors: one intra-op thread is much faster than two on a shared 2-core
machine (OpenMP workers spin while other processes hold the cores), so pin it and restore afterwards."""

import pytest
import torch


@pytest.fixture(autouse=True, scope="module")
def single_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
