"""Project-wide test settings.

Every test runs with one intra-op thread: the tensors are tiny, and on a shared 2-core machine spinning
OpenMP workers made the suite 5-20x slower (measured by the package helpers). The setting is session-wide
and autouse, so it is in force before any session fixture (e.g. the prepared cache) is built.
"""

import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def single_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
