"""Run this area's tests on one torch thread.

On the shared 2-core test machine, two OpenMP threads competing with other processes made
a tiny training step ~100x slower (spin-waiting); one thread is fast and deterministic.
"""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
